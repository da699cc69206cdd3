"""The `qnav` console command in a process of its own, as a user runs it."""

import subprocess
import sys


def run_qnav(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess[str]:
    """Run `qnav ARGS...` to its end; its exit code, stdout and stderr come back as text."""
    return subprocess.run(
        [sys.executable, "-m", "qnav", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )
