"""`trundle demo`: the simulated robot recorded by the real daemon, replayed through SLAM and markers, scored."""
