"""Liveness files: each daemon's working loop proves it still turns; `qnav health` reads the proof.

With `QNAV_HEALTH_FILE` set (the runtime image sets it), the controller, the bridge and the
recorder rewrite that file at most once a second from the loop that does their work, not from a
side thread, so a wedged loop goes stale even while the process lives. `qnav health` (the
image's HEALTHCHECK) exits 0 only while the newest beat is younger than `--max-age-s`.

Ages use the shared CLOCK_MONOTONIC (`time.monotonic()` on Linux is the same clock in every
process of one boot), so a wall clock that jumps when the car's computer finds NTP cannot make a
live daemon look dead. A daemon that ends cleanly deletes its file.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HEALTH_FILE_ENV = "QNAV_HEALTH_FILE"
"""Environment variable naming the health file; unset: no file is written."""

DEFAULT_MAX_AGE_S = 5.0
"""A beat older than this makes `qnav health` fail."""

log = logging.getLogger(__name__)


def health_path(environ: dict[str, str] | None = None) -> Path | None:
    """The health file named by the environment, or None."""
    value = (os.environ if environ is None else environ).get(HEALTH_FILE_ENV, "")
    return Path(value) if value else None


@dataclass
class Heartbeat:
    """Rewrites one daemon's health file, atomically, at most once per `every_s`."""

    daemon: str
    """Which daemon beats ("controller", "bridge", "recorder")."""
    path: Path | None
    """The health file; None: beats do nothing."""
    every_s: float = 1.0
    """Least time between two writes."""
    _last_s: float = field(default=-math.inf, repr=False)
    _failed: bool = field(default=False, repr=False)

    @classmethod
    def from_env(cls, daemon: str) -> Heartbeat:
        """A heartbeat to the file `QNAV_HEALTH_FILE` names (none if unset)."""
        return cls(daemon, health_path())

    def beat(self, **detail: Any) -> None:
        """Prove the loop turns; `detail` (JSON values) is shown by `qnav health`."""
        if self.path is None:
            return
        now = time.monotonic()
        if now - self._last_s < self.every_s:
            return
        self._last_s = now
        record = {
            "daemon": self.daemon,
            "pid": os.getpid(),
            "monotonic_s": now,
            "time_unix_s": time.time(),
            "detail": detail,
        }
        partial = self.path.with_name(f".{self.path.name}.{os.getpid()}")
        try:
            partial.write_text(json.dumps(record))
            os.replace(partial, self.path)  # a reader sees the old beat or the new one, whole
            self._failed = False
        except OSError as error:
            if not self._failed:  # once per failure streak: a full disk must not flood the log
                log.warning("cannot write the health file %s: %s", self.path, error)
            self._failed = True

    def close(self) -> None:
        """The daemon ends cleanly: remove its file, so nothing reads it as alive."""
        if self.path is not None:
            self.path.unlink(missing_ok=True)


def check_health(
    path: Path, max_age_s: float = DEFAULT_MAX_AGE_S, now_s: float | None = None
) -> tuple[bool, str]:
    """(healthy, a one-line explanation) for the health file at `path`."""
    try:
        record = json.loads(path.read_text())
        age_s = (time.monotonic() if now_s is None else now_s) - float(record["monotonic_s"])
        who = f"{record['daemon']} (pid {record['pid']})"
    except FileNotFoundError:
        return False, (
            f"no health file at {path}: the daemon has not started its loop, has ended, or "
            f"writes elsewhere ({HEALTH_FILE_ENV} must be the same for both)"
        )
    except (OSError, ValueError, KeyError, TypeError) as error:
        return False, f"unreadable health file {path}: {error}"
    detail = ", ".join(f"{k}={v}" for k, v in record.get("detail", {}).items())
    suffix = f" [{detail}]" if detail else ""
    if age_s > max_age_s:
        return False, f"{who}: last beat {age_s:.1f} s ago (limit {max_age_s:g} s){suffix}"
    return True, f"{who}: last beat {age_s:.1f} s ago{suffix}"
