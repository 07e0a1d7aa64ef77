"""One-log jobs: each reads one log, writes its outputs and returns a JSON-able report; the
`trundle` commands and the fleet run the same code."""
