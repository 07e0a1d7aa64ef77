"""Device emulators: the device side of each protocol on a pty, TCP port or CAN bus."""
