"""ArduPilot Rover SITL as a process, for `qnav stack --vehicle sitl` (docs/bridge.md).

The binary is the user's (never vendored; docs/bridge.md, "Getting a SITL binary"). It runs
wiped (`-w`) in a work folder with our parameter files, SERIAL0 (TCP base port) for the
sim-car's pose reader and SERIAL1 (base port + 2) for the bridge, as a companion computer on a
telemetry port. The autopilot serves TCP ports without authentication: run it only where
nothing else can reach them (`network_is_isolated`, `make stack-sitl`: `unshare --net`).
"""

from __future__ import annotations

import os
import socket
import subprocess
import time
from pathlib import Path

from qnav.contracts.daemon import stop_process
from qnav.contracts.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SITL_PARAMS = ROOT / "config" / "ardupilot-sitl.parm"
"""Failsafes, stream rates and RC ranges (the same as the SITL tests')."""
SKID_PARAMS = ROOT / "config" / "ardupilot-sitl-skid.parm"
"""A skid-steered rover: it turns in place, as the policy's turn actions ask."""
SITL_ENV = "ARDUPILOT_SITL"
HOME = "-35.363261,149.165230,584,0"
"""ArduPilot's SITL home (CMAC), heading north."""


def sitl_binary_from_env() -> Path | None:
    """The ardurover binary named by ARDUPILOT_SITL, or None."""
    value = os.environ.get(SITL_ENV, "")
    return Path(value) if value else None


def network_is_isolated() -> bool:
    """True when loopback is this network namespace's only interface (`unshare --net`)."""
    try:  # the kernel's list for this process's namespace (/sys may show the host's)
        interfaces = [name for _, name in socket.if_nameindex()]
    except OSError:
        return False
    return interfaces == ["lo"]


def port_is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_instance() -> int:
    """A SITL instance number whose TCP ports (5760 + 10 i ... + 3) are free."""
    for instance in range(40):
        base = 5760 + 10 * instance
        if all(port_is_free(base + offset) for offset in range(4)):
            return instance
    raise RuntimeError("no free SITL instance among 0..39")


class SitlProcess:
    """One `ardurover` process in a work folder of its own."""

    def __init__(
        self, binary: Path, workdir: Path, params: list[Path], model: str = "rover"
    ) -> None:
        if not binary.is_file():
            raise ConfigError(f"--sitl-binary {binary} is not a file (docs/bridge.md)")
        self.binary, self.workdir, self.params, self.model = binary, workdir, params, model
        self.instance = free_instance()
        self.base_port = 5760 + 10 * self.instance
        self.log_path = workdir / "ardurover.log"
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def serial0(self) -> str:
        """SERIAL0 ("USB": unsigned packets always accepted): the pose reader's port."""
        return f"tcp:127.0.0.1:{self.base_port}"

    @property
    def serial1(self) -> str:
        """SERIAL1, a telemetry port: the bridge's."""
        return f"tcp:127.0.0.1:{self.base_port + 2}"

    def command_line(self) -> list[str]:
        return [
            str(self.binary.resolve()),
            "-w",
            "--model", self.model,
            "--speedup", "1",
            "--home", HOME,
            "--defaults", ",".join(str(p.resolve()) for p in self.params),
            "--serial0", "tcp:0",
            "--serial1", "tcp:2",
            "-I", str(self.instance),
        ]  # fmt: skip

    def start(self, timeout_s: float = 20.0) -> None:
        """Start it and wait for its serial ports to listen."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("wb") as out:
            self.process = subprocess.Popen(
                self.command_line(), cwd=self.workdir, stdout=out, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + timeout_s
        while port_is_free(self.base_port + 2):
            if self.process.poll() is not None:
                raise RuntimeError(f"ardurover exited; see {self.log_path}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"ardurover's ports did not open in {timeout_s} s")
            time.sleep(0.1)

    def stop(self) -> None:
        if self.process is None:
            return
        stop_process(self.process, timeout_s=5.0)
        self.process = None
