"""What every daemon needs, written once: a rate-limited warning log, stop on signals, a port,
and ending a child process in order (SIGTERM, then SIGKILL if it hangs).

The onboard daemons (`controller`, `firmware_bridge`) import only `contracts`, so these live
here; the simulator's processes, the recorder, the policy server and the tests use them too.
"""

from __future__ import annotations

import logging
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType, TracebackType
from typing import Any, Self

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals that end a daemon in order (its stops sent, its session closed)."""


class RateLimitedLog:
    """Warnings of one kind at most once per interval; the ones held back are counted and the
    next warning of that kind says how many (malformed payloads may arrive at the sensor rate).

    Safe from several threads. `now` is the caller's monotonic time in seconds (an I/O-free
    decision core passes its own); without it the log reads `clock`.
    """

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._clock = clock
        self._last_s: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def warning(
        self, kind: str, message: str, now: float | None = None, *, exc_info: bool = False
    ) -> bool:
        """Log `message` unless one of this `kind` was logged less than an interval ago (then
        count it); True if it was logged. `exc_info`: with the traceback of the exception being
        handled."""
        now = self._clock() if now is None else now
        with self._lock:
            last = self._last_s.get(kind)
            if last is not None and now - last < self.interval_s:
                self._held[kind] = self._held.get(kind, 0) + 1
                return False
            self._last_s[kind] = now
            held = self._held.pop(kind, 0)
        suffix = f" ({held} more since the last warning)" if held else ""
        self.logger.warning("%s%s", message, suffix, exc_info=exc_info)
        return True


class Service:
    """Something started and closed (a daemon, a test vehicle): `start()` it and `close()` it,
    or use it as `with Thing(...) as thing:`."""

    def start(self) -> None:
        """Start working (threads, connections)."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop working and release what `start` took."""
        raise NotImplementedError

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self.close()


@contextmanager
def stop_on_signals(
    stop: threading.Event | None = None, logger: logging.Logger | None = None
) -> Iterator[threading.Event]:
    """Within the block, SIGINT and SIGTERM set `stop` (a new event if None, yielded) instead
    of raising, logged as "SIGTERM: stopping" on `logger` if given; the handlers that were
    there before come back when the block ends. Call from the main thread."""
    event = threading.Event() if stop is None else stop

    def on_signal(number: int, frame: FrameType | None) -> None:
        if logger is not None:
            logger.info("%s: stopping", signal.Signals(number).name)
        event.set()

    previous = {number: signal.signal(number, on_signal) for number in STOP_SIGNALS}
    try:
        yield event
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that nothing uses right now (TCP by default; SOCK_DGRAM for UDP)."""
    with socket.socket(socket.AF_INET, kind) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def stop_process(process: subprocess.Popen[Any], timeout_s: float = 10.0) -> bool:
    """SIGTERM `process` and wait for it to end; SIGKILL it if it still runs after `timeout_s`.
    True if it ended on the SIGTERM (in order, its stops sent); False if it had to be killed.
    Output it writes to a pipe is read meanwhile (so a full pipe cannot hold it up) and dropped."""
    process.send_signal(signal.SIGTERM)
    try:
        process.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        return False
    return True
