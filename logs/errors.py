"""The error hierarchy, shaped like python-can's (CanError -> Initialization/Operation/Timeout).

``TrundleError`` is the base. Below it:

- ``UserError``: the user's input is wrong (bad path, bad command line, unknown device); its
  kinds ``ConfigError`` (a config key or value: names the key, the value and what was expected)
  and ``UsageError`` (the command line).
- ``DataError``: input data that is corrupt or unusable (a damaged log, a file of the wrong
  format, a log without the messages a job needs).
- ``OutputError``: an output could not be written (a read-only folder, a full disk, a quota): not
  the user's mistake, said in one line naming the path and the cause, exit code 1; nothing
  half-written is left behind (:mod:`trundle.logs.outputs`).
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


class OutputError(TrundleError):
    """An output could not be written (read-only folder, full disk, quota): names the path and the cause.

    ``path`` is the file being written and ``cause`` the OSError, when known, so a writer of a
    temporary file can say it again under the name the user gave."""

    def __init__(self, message: str, path: str | None = None, cause: OSError | None = None) -> None:
        super().__init__(message)
        self.path = path
        self.cause = cause


class DeviceError(TrundleError):
    """A device failed: no answer, a broken link or a reply the protocol does not allow."""


class ProtocolError(DeviceError):
    """The device answered, but not as its protocol says (bad checksum, bad status, bad frame)."""


class TransportError(DeviceError):
    """The port, socket or bus underneath the device failed or cannot be opened."""


class PortBusyError(TransportError):
    """The port is held by another program (its lock is taken): a command ends on it at once, the
    daemon says it and retries, since the other program may let go."""
