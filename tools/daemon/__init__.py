"""The onboard service: life cycle, supervision, online processing, status socket, systemd, disk guard, config."""
