"""The robot configuration (``robot.toml``): one model and one validator for every command that reads it."""
