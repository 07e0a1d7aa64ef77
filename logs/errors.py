"""The error hierarchy, shaped like python-can's (CanError -> Initialization/Operation/Timeout).

``TrundleError`` is the base. Below it:

- ``UserError``: the user's input is wrong (bad path, bad command line, unknown device); its
  kinds ``ConfigError`` (a config key or value: names the key, the value and what was expected)
  and ``UsageError`` (the command line).
- ``DataError``: input data that is corrupt or unusable (a damaged log, a file of the wrong
  format, a log without the messages a job needs).
- ``DeviceError``: a device failed: ``ProtocolError`` (it answered, but not as the protocol
  says) or ``TransportError`` (the port, socket or bus itself; ``PortBusyError``: another program
  holds the port).

The command line prints any ``TrundleError`` as one line on stderr and exits non-zero, never a
traceback. A driver's life cycle catches ``DeviceError`` and ``OSError`` only, so a programming
bug (``ValueError``, ``KeyError``, ...) surfaces as a crash with its traceback.
"""


class TrundleError(Exception):
    """Base of every error trundle raises on purpose, said as one clear line."""


class UserError(TrundleError):
    """A problem with the user's input, reported as one clear line."""


class ConfigError(UserError):
    """A config key or value that is not allowed: names the key, the value and the expectation."""


class UsageError(UserError):
    """A command-line mistake (an option's value, a missing argument)."""


class DataError(TrundleError):
    """Input data that is corrupt or unusable: a damaged log, a file of the wrong format."""


class DeviceError(TrundleError):
    """A device failed: no answer, a broken link or a reply the protocol does not allow."""


class ProtocolError(DeviceError):
    """The device answered, but not as its protocol says (bad checksum, bad status, bad frame)."""


class TransportError(DeviceError):
    """The port, socket or bus underneath the device failed or cannot be opened."""


class PortBusyError(TransportError):
    """The port is held by another program (its lock is taken): a command ends on it at once, the
    daemon says it and retries, since the other program may let go."""
