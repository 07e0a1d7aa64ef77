"""The `trundle` command line, the onboard daemon, device emulators, world simulator, benchmarks."""
