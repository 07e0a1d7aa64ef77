"""``Driver.run`` reconnects on device faults only: a bug (ValueError, KeyError, ...) ends the
run with its own exception and marks the driver crashed instead of reconnecting forever."""

from __future__ import annotations

import pytest
import serial

from trundle.drivers.lifecycle import Backoff, Driver
from trundle.logs import messages as m
from trundle.logs.errors import DeviceError, ProtocolError, TransportError


class RecordingBackoff(Backoff):
    """A back-off that records the delays it hands out (s)."""

    def __init__(self) -> None:
        super().__init__(0.001, 0.004)
        self.delays: list[float] = []

    def next_delay(self) -> float:
        delay = super().next_delay()
        self.delays.append(delay)
        return delay


class FailingDriver(Driver):
    """Raises ``error`` from ``read_once`` (or ``open`` when ``in_open``) ``times`` times, then finishes."""

    def __init__(self, error: BaseException, times: int = 1, in_open: bool = False) -> None:
        super().__init__("test", lambda topic, msg, t: None, hardware_id="test:0", backoff=RecordingBackoff())
        self.error, self.left, self.in_open = error, times, in_open
        self.opened = self.closed = 0

    def open(self) -> None:
        self.opened += 1
        if self.in_open and self.left:
            self.left -= 1
            raise self.error

    def read_once(self) -> None:
        if self.left:
            self.left -= 1
            raise self.error
        self.finish()

    def close(self) -> None:
        self.closed += 1


@pytest.mark.parametrize("error", [ValueError("bad index math"), KeyError("missing"), TypeError("None + 1")])
@pytest.mark.parametrize("in_open", [False, True])
def test_a_bug_ends_the_run_with_its_own_error(error, in_open):
    driver = FailingDriver(error, times=5, in_open=in_open)
    with pytest.raises(type(error)) as raised:
        driver.run()
    assert raised.value is error and raised.value.__traceback__ is not None
    assert (driver.opened, driver.closed, driver.counters["reconnects"], driver.counters["errors"]) == (1, 1, 0, 0)
    assert driver.backoff.delays == [] and driver.open_error == ""
    assert driver.state == "crashed" and driver.last_error == f"{type(error).__name__}: {error}"
    status = driver.diagnostics()
    assert status.level == m.ERROR and status.message == f"driver crashed: {type(error).__name__}: {error}"


@pytest.mark.parametrize("error", [DeviceError("unplugged"), ProtocolError("bad checksum"), TransportError("EIO"),
                                   OSError(5, "Input/output error"), serial.SerialException("read failed")])
def test_a_device_fault_reconnects_with_back_off(error):
    driver = FailingDriver(error, times=4)
    driver.run()
    assert driver.state == "stopped" and driver.opened == 5 and driver.closed == 5
    assert driver.counters["reconnects"] == 4 and driver.counters["errors"] == 4
    assert driver.backoff.delays == [0.001, 0.001, 0.001, 0.001]  # each reconnect opened: the back-off resets
    assert driver.last_error == f"{type(error).__name__}: {error}"


def test_a_device_that_cannot_be_opened_backs_off_doubling_and_names_the_cause():
    driver = FailingDriver(OSError(2, "No such file or directory", "/dev/ttyACM9"), times=4, in_open=True)
    seen: list[tuple[int, str]] = []
    driver.close = lambda: seen.append(driver.health_status(0.0))  # type: ignore[method-assign]
    driver.run()
    assert driver.backoff.delays == [0.001, 0.002, 0.004, 0.004]
    assert (driver.opened, driver.counters["reconnects"], driver.counters["errors"]) == (5, 0, 4)
    assert seen[0] == (m.ERROR, "cannot open test:0: [Errno 2] No such file or directory: '/dev/ttyACM9' "
                                "(not plugged in, or a wrong path)")
