"""What a user configures, checked: the robot configuration (``robot.toml``: one model and one
validator for every command that reads it) and the ranges of command-line options."""
