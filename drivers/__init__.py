"""Device I/O only: bytes in, typed messages out (codec + transport + driver + emulator)."""
