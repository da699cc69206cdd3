"""Life cycle shared by the daemons (controller, bridge, recorder): signals, zenoh, warnings.

Every daemon must end within a second of SIGTERM or SIGINT in every state: before its zenoh
router is reachable, connected, and after losing it. Two things stood in the way: a client
session's `zenoh.open` waits for its router without end (and a Python signal handler only runs
once the main thread is back from native code), and the signal handlers were installed around
that wait. Here the handlers only set an event, and the session is opened in a worker thread
while the caller waits on that event, so a signal ends the wait at once.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

from contracts.errors import ConfigError
from contracts.transport import ZenohSettings, zenoh_config

POLL_S = 0.05
"""How often a wait for the session looks at whether it opened (the stop event wakes it)."""
WAITING_LOG_S = 10.0
"""While the router stays unreachable, say so this often."""


@contextmanager
def stop_on_signals(
    logger: logging.Logger, stop: threading.Event | None = None
) -> Iterator[threading.Event]:
    """An event that SIGINT or SIGTERM sets (the previous handlers come back on exit).

    Call from the main thread. The handler only logs and sets the event: whatever waits on it
    (the daemon's loop, `open_session_until`) then shuts down in order.
    """
    event = stop or threading.Event()

    def on_signal(number: int, frame: FrameType | None) -> None:
        logger.info("%s: stopping", signal.Signals(number).name)
        event.set()

    previous = {
        number: signal.signal(number, on_signal) for number in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        yield event
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def open_session_until(
    settings: ZenohSettings, stop: threading.Event, logger: logging.Logger
) -> Any | None:
    """An open zenoh session, or None when `stop` was set before one opened.

    The session opens in a worker thread (a client waits there for its router, however long);
    this thread returns as soon as `stop` is set. A session that opens after that is closed by
    the worker. A zenoh configuration it refuses raises ConfigError, as `open_session` does.
    """
    import zenoh

    config = zenoh_config(settings)  # a bad setting fails here, before any thread
    done = threading.Event()
    lock = threading.Lock()
    outcome: dict[str, Any] = {}

    def opener() -> None:
        try:
            session = zenoh.open(config)
        except Exception as error:  # zenoh raises its own error type
            outcome["error"] = error
            done.set()
            return
        with lock:
            abandoned = "taken" in outcome  # the caller stopped waiting: nobody will close it
            if not abandoned:
                outcome["session"] = session
        if abandoned:
            session.close()  # type: ignore[no-untyped-call]
        done.set()

    if settings.session_mode == "client" and not settings.config_file:
        logger.info(
            "zenoh: connecting to %s (waiting until something listens there)",
            ", ".join(settings.connect),
        )
    threading.Thread(target=opener, name="zenoh-open", daemon=True).start()
    started = time.monotonic()
    next_log = started + WAITING_LOG_S
    while not done.wait(POLL_S):
        if stop.is_set():
            with lock:
                if "session" not in outcome:
                    outcome["taken"] = None  # the worker closes what opens from now on
                    logger.info("zenoh: stopped before a session opened")
                    return None
            break
        if time.monotonic() >= next_log:
            next_log += WAITING_LOG_S
            logger.warning(
                "zenoh: still no session after %.0f s (connect %s)",
                time.monotonic() - started,
                list(settings.connect),
            )
    with lock:
        outcome["taken"] = None
        if "error" in outcome:
            raise ConfigError(
                f"cannot open a zenoh session (listen {list(settings.listen)}, "
                f"connect {list(settings.connect)}): {outcome['error']}"
            )
        return outcome["session"]


class RateLimitedLog:
    """Warnings that may repeat fast (malformed payloads), at most one per key and period."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0) -> None:
        self._logger = logger
        self._period_s = period_s
        self._last_s: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()
        self._lock = threading.Lock()

    def warning(self, what: str, message: str, *args: object) -> None:
        """Log `message` unless `what` was logged within the period (then count it)."""
        now = time.monotonic()
        with self._lock:
            if now - self._last_s.get(what, -math.inf) < self._period_s:
                self._suppressed[what] += 1
                return
            self._last_s[what] = now
            suppressed, self._suppressed[what] = self._suppressed[what], 0
        suffix = f" ({suppressed} more since the last report)" if suppressed else ""
        self._logger.warning(message + suffix, *args)
