"""The daemons' shared parts: the rate-limited log, stopping on signals, a free port, ending a
child process."""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from qnav.contracts.daemon import (
    RateLimitedLog,
    Service,
    free_port,
    stop_on_signals,
    stop_process,
)


def test_malformed_input_warnings_are_logged_at_a_bounded_rate(
    caplog: pytest.LogCaptureFixture,
) -> None:
    bounded = RateLimitedLog(logging.getLogger("test.bounded"), interval_s=5.0)
    with caplog.at_level(logging.WARNING, "test.bounded"):
        logged = [bounded.warning("scan", "scan refused", t * 0.1) for t in range(100)]
        bounded.warning("pose", "pose refused", 0.0)
    assert logged.count(True) == 2  # at 0 s and 5 s
    assert [r.message for r in caplog.records] == [
        "scan refused",
        "scan refused (49 more since the last warning)",
        "pose refused",
    ]


def test_without_a_time_the_log_reads_its_clock(caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    bounded = RateLimitedLog(logging.getLogger("test.clock"), interval_s=1.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, "test.clock"):
        assert bounded.warning("x", "first")
        now[0] = 0.5
        assert not bounded.warning("x", "held")
        now[0] = 1.0
        assert bounded.warning("x", "again")
    assert [r.message for r in caplog.records] == ["first", "again (1 more since the last warning)"]


def test_a_warning_may_carry_the_traceback_of_the_exception_being_handled(
    caplog: pytest.LogCaptureFixture,
) -> None:
    bounded = RateLimitedLog(logging.getLogger("test.trace"), interval_s=5.0)
    with caplog.at_level(logging.WARNING, "test.trace"):
        for now in (0.0, 1.0):
            try:
                raise OSError("disk full")
            except OSError:
                bounded.warning("write", "cannot write", now, exc_info=True)
    (record,) = caplog.records
    assert record.exc_info is not None and record.exc_info[0] is OSError


@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_sets_the_stop_event_and_the_old_handler_comes_back(
    number: signal.Signals, caplog: pytest.LogCaptureFixture
) -> None:
    before = signal.getsignal(number)
    given = threading.Event()
    logger = logging.getLogger("test.signals")
    with caplog.at_level(logging.INFO, "test.signals"), stop_on_signals(given, logger) as stop:
        assert stop is given and not stop.is_set()
        os.kill(os.getpid(), number)  # handled in this (main) thread
        assert stop.wait(5.0)
    assert signal.getsignal(number) is before
    assert caplog.records[-1].message == f"{number.name}: stopping"


def test_a_free_port_can_be_bound_for_tcp_and_udp() -> None:
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        port = free_port(kind)
        with socket.socket(socket.AF_INET, kind) as sock:
            sock.bind(("127.0.0.1", port))
            assert sock.getsockname()[1] == port


def _python(code: str) -> subprocess.Popen[bytes]:
    """A child Python running `code`, once it has printed that it is ready."""
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert child.stdout is not None and child.stdout.readline() == b"ready\n"
    return child


def test_a_child_that_ends_on_sigterm_is_stopped_in_order_and_one_that_hangs_is_killed() -> None:
    obeys = _python(
        "import signal, sys, time\n"
        "signal.signal(signal.SIGTERM, lambda *_: sys.exit(3))\n"
        "print('ready', flush=True)\n"
        "time.sleep(60)"
    )
    assert stop_process(obeys, timeout_s=10.0)
    assert obeys.returncode == 3  # its own handler ran
    hangs = _python(
        "import signal, time\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "print('ready', flush=True)\n"
        "time.sleep(60)"
    )
    started = time.monotonic()
    assert not stop_process(hangs, timeout_s=0.5)
    assert hangs.returncode == -signal.SIGKILL
    assert time.monotonic() - started < 10.0


def test_a_service_in_a_with_block_is_started_and_closed_even_on_an_error() -> None:
    calls: list[str] = []

    class Thing(Service):
        def start(self) -> None:
            calls.append("start")

        def close(self) -> None:
            calls.append("close")

    with pytest.raises(RuntimeError), Thing() as thing:
        assert isinstance(thing, Thing) and calls == ["start"]
        raise RuntimeError("inside")
    assert calls == ["start", "close"]
