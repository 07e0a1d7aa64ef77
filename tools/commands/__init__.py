"""One module per `trundle` sub-command; each defines ``register(subparsers)``."""
