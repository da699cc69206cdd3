"""The whole system as separate processes on loopback: sim-car, controller, bridge, recorder.

`qnav stack --policy FILE` writes the daemons' configuration files, starts

    qnav sim-car     the simulated world: LaserScan and PoseStamped out on zenoh (the hub the
                     others connect to), its car a MAVLink vehicle on a UDP port
    qnav controller  the policy file, deciding on each scan
    qnav bridge      Twist to RC overrides over MAVLink, arming the car
    qnav record      every topic to MCAP
    qnav serve       with `--serve-folder DIR --keys KEYS`: the policies in DIR, signed, to the
                     controller, which starts on the policy file and swaps a better one in at a
                     stop (policy.source = "server", docs/serve.md)

as a user would start them, waits for the sim-car's episodes, stops the daemons with SIGTERM and
reports the outcomes beside `qnav eval` of the same file on the same episodes.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from types import FrameType
from typing import IO, TYPE_CHECKING, Any

from qnav.contracts.daemon import free_port
from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import from_dict, to_toml
from qnav.verbs.parser import Verbs, flag, lookahead_option, verb

if TYPE_CHECKING:
    from qnav.controller.lookahead import LookaheadSettings
    from qnav.controller.proximity import ProximitySettings
    from qnav.sim.config import WorldConfig
    from qnav.sim.evaluate import Agent
    from qnav.sitl import SitlProcess


@dataclass(frozen=True)
class StackFiles:
    """Where one stack run keeps its configuration, logs and outputs."""

    root: Path
    """The run's folder."""

    @property
    def controller_toml(self) -> Path:
        """The controller's configuration."""
        return self.root / "controller.toml"

    @property
    def bridge_toml(self) -> Path:
        """The bridge's configuration."""
        return self.root / "bridge.toml"

    @property
    def episodes(self) -> Path:
        """The sim-car's episode log (JSON lines)."""
        return self.root / "episodes.jsonl"

    @property
    def recording(self) -> Path:
        """The MCAP recording folder."""
        return self.root / "recording"

    def log(self, name: str) -> Path:
        """A daemon's stderr."""
        return self.root / f"{name}.log"


@dataclass(frozen=True)
class StackServe:
    """`qnav serve` in the stack: what it serves and the key pair it signs with."""

    folder: Path
    """The folder it serves (exported policy files, or run folders)."""
    keys: Path
    """The folder `qnav keys` wrote the key pair into."""
    poll_s: float = 0.5
    """How often the server looks at the folder."""
    announce_interval_s: float = 1.0
    """How often it repeats its announcement."""
    rest_s: float = 1.0
    """The sim-car's rest after each episode (`sim-car --rest-s`): the stop at which the
    controller may swap a delivered policy in (without one, the next target follows at once and
    the car is never at rest while the stack runs)."""

    @property
    def private_key(self) -> Path:
        """The server's signing key."""
        from qnav.contracts.delivery import PRIVATE_KEY_FILE

        return self.keys / PRIVATE_KEY_FILE

    @property
    def public_key(self) -> Path:
        """The key the controller trusts."""
        from qnav.contracts.delivery import PUBLIC_KEY_FILE

        return self.keys / PUBLIC_KEY_FILE

    def check(self) -> None:
        """ConfigError naming the option if a path is missing."""
        if not self.folder.is_dir():
            raise ConfigError(f"--serve-folder {self.folder} is not a folder")
        for key in (self.private_key, self.public_key):
            if not key.is_file():
                raise ConfigError(f"--keys {self.keys}: no {key.name} (make one with qnav keys)")


def sitl_bridge_settings(connection: str) -> dict[str, Any]:
    """The bridge on the firmware: GUIDED velocity and yaw rate (Rover's own speed and turn-rate
    controllers, braking on a stop), SITL's GPS as the EKF's position (no pose forwarded), and
    the ground-station heartbeat well within FS_GCS_TIMEOUT (config/bridge-sitl.toml)."""
    return {
        "mavlink": {"connection": connection, "heartbeat_period_s": 0.1},
        "output": {"mode": "guided"},
        "vision": {"forward_pose": False},
        "vehicle": {"arm_on_connect": True, "set_mode_on_connect": True},
    }


def write_configs(
    files: StackFiles,
    policy: Path,
    zenoh_endpoint: str,
    mavlink_port: int,
    tolerance_m: float,
    *,
    bridge_values: dict[str, Any] | None = None,
    public_key: Path | None = None,
    input_timeout_s: float = 0.0,
    lookahead: LookaheadSettings | None = None,
    proximity: ProximitySettings | None = None,
) -> None:
    """The controller's and the bridge's TOML files for this stack (`bridge_values`: the
    bridge's settings other than zenoh, instead of the test vehicle's; `public_key`: the
    controller takes policies from a server signed with its private key, `policy` first;
    `input_timeout_s`: the controller's scan and pose timeouts, 0 for its default;
    `lookahead`: the controller's look ahead, with its room (`tracking.room_of`), and its
    proximity stop, `proximity` or the default field; None: the policy alone, neither)."""
    from qnav.controller.config import DaemonConfig
    from qnav.firmware_bridge.settings import BridgeSettings
    from qnav.simcar.car import SimCarSettings

    zenoh = {"connect": [zenoh_endpoint], "listen": []}
    controller = from_dict(
        DaemonConfig,
        {
            "controller": {"policy": str(policy.resolve()), "trigger": "scan"},
            "safety": {"target_tolerance_m": tolerance_m}
            | (
                {}
                if input_timeout_s <= 0
                else {"scan_timeout_s": input_timeout_s, "pose_timeout_s": input_timeout_s}
            ),
            "zenoh": zenoh,
        }
        | _lookahead_tables(lookahead, proximity)
        | (
            {}
            if public_key is None
            else {
                "policy": {
                    "source": "server",
                    "public_key": str(public_key.resolve()),
                    "cache_dir": str((files.root / "policy-cache").resolve()),
                }
            }
        ),
    )
    full_travel = SimCarSettings().full_throttle_speed_mps  # the test vehicle's, known exactly
    values = bridge_values or {
        "mavlink": {"connection": f"udpout:127.0.0.1:{mavlink_port}"},
        "vehicle": {"arm_on_connect": True, "set_mode_on_connect": True},
        "output": {
            "speed_at_full_throttle_mps": full_travel,
            "turn_rate_at_full_steering_radps": full_travel,
        },
        # The simulated car ends with the stack (the sim-car stops with the bridge): nothing
        # reports its rest on the way out, so the bridge disarms at once instead of waiting.
        "failsafe": {"rest_timeout_s": 0.0},
    }
    bridge = from_dict(BridgeSettings, {**values, "zenoh": zenoh})
    files.root.mkdir(parents=True, exist_ok=True)
    files.controller_toml.write_text(to_toml(controller))
    files.bridge_toml.write_text(to_toml(bridge))


def qnav_child(
    args: Sequence[str], *, stdout: int | IO[str], stderr: int | IO[str]
) -> subprocess.Popen[str]:
    """`qnav ARGS...` in a child process, its numerics on one thread (children share the
    machine's cores with each other and with this process)."""
    env = os.environ | {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "qnav", *args]
    return subprocess.Popen(command, stdout=stdout, stderr=stderr, text=True, env=env)


class Daemons:
    """Child processes started as a user would start them; stopped with SIGTERM."""

    def __init__(self, files: StackFiles) -> None:
        self.files = files
        self.processes: dict[str, subprocess.Popen[str]] = {}
        self._logs: list[IO[str]] = []

    def start(self, name: str, *args: str, stdout: int | None = None) -> subprocess.Popen[str]:
        """`qnav ARGS...`, stderr to `<name>.log`."""
        log = self.files.log(name).open("w")
        self._logs.append(log)
        process = qnav_child(args, stdout=stdout if stdout is not None else log, stderr=log)
        self.processes[name] = process
        return process

    def check_alive(self) -> None:
        """Raise if a daemon died."""
        for name, process in self.processes.items():
            if process.poll() is not None and name != "sim-car":
                tail = self.files.log(name).read_text().strip().splitlines()[-5:]
                raise RuntimeError(
                    f"{name} exited with code {process.returncode}:\n  " + "\n  ".join(tail)
                )

    def stop(self, timeout_s: float = 10.0) -> dict[str, int | None]:
        """SIGTERM every daemon still running, then wait (SIGKILL after `timeout_s`).

        The recorder goes last, so the stop commands the others send on exit are recorded.
        """
        codes: dict[str, int | None] = {}
        last = ["recorder"]
        for group in ([n for n in self.processes if n not in last], last):
            running = [(n, self.processes[n]) for n in group if n in self.processes]
            for _, process in running:
                if process.poll() is None:
                    process.send_signal(signal.SIGTERM)
            for name, process in running:
                try:
                    codes[name] = process.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    process.kill()
                    codes[name] = process.wait()
        for log in self._logs:
            log.close()
        return codes


def run_stack(
    policy: Path,
    out: Path,
    *,
    scenario: str | None = None,
    episodes: int = 20,
    first_episode: int = 0,
    record: bool = True,
    progress: bool = True,
    sitl_binary: Path | None = None,
    serve: StackServe | None = None,
    lockstep: bool = True,
    lookahead: LookaheadSettings | None = None,
    lidar_turn_s: float = 0.0,
) -> dict[str, Any]:
    """Run the full stack for `episodes` episodes; returns its outcome fractions and paths.

    With `serve`, `qnav serve` runs on the stack's hub too and the controller takes its policies
    from it, starting on `policy`; the sim-car rests `serve.rest_s` after each episode.

    With `sitl_binary`, the car is ArduPilot Rover SITL (a skid-steered rover, `qnav.sitl`):
    the bridge drives it in GUIDED and the sim-car takes the robot's pose from the autopilot's
    own LOCAL_POSITION_NED and ATTITUDE, simulating lidar and walls around it.

    With `lockstep` (the test vehicle only), the sim-car steps the world once the command
    decided on each scan has reached the car (`sim-car --lockstep`); else in real time.

    `lookahead` is the controller's look ahead (`controller.lookahead`; None: off).

    With `lidar_turn_s`, the world's lidar rotates (its `lidar_turn_s`): each scan's beams leave
    over that many seconds while the car and the obstacles move (lockstep only).
    """
    from qnav.contracts.policy_file import PolicyContract
    from qnav.controller.onnx_file import read_onnx
    from qnav.sim.config import scenario as load_scenario

    contract = PolicyContract.from_metadata(read_onnx(policy).metadata, str(policy))
    world = replace(load_scenario(scenario or contract.scenario), lidar_turn_s=lidar_turn_s)
    files = StackFiles(out)
    hub = f"tcp/127.0.0.1:{free_port()}"
    lockstep = lockstep and sitl_binary is None  # the firmware keeps its own time
    vehicle = _vehicle(files, lockstep, sitl_binary, lidar_turn_s)
    _configure(
        files, policy, hub, vehicle, world, lockstep=lockstep, serve=serve, lookahead=lookahead
    )
    sim_car_args = [
        "--scenario", world.name, "--episodes", str(episodes),
        "--first-episode", str(first_episode), "--listen", hub, *vehicle.args,
        "--log", str(files.episodes), *([] if serve is None else ["--rest-s", str(serve.rest_s)]),
    ]  # fmt: skip
    daemons = Daemons(files)
    started = time.monotonic()
    try:
        if vehicle.sitl is not None:
            vehicle.sitl.start()
        _start_daemons(daemons, files, hub, record, serve)
        outcomes, steps = _drive(daemons, files, sim_car_args, episodes, progress)
    finally:
        codes = daemons.stop()
        if vehicle.sitl is not None:
            vehicle.sitl.stop()
    count = max(len(outcomes), 1)
    return {
        "policy": str(policy),
        "scenario": world.name,
        "episodes": len(outcomes),
        **{name: outcomes.count(name) / count for name in ("success", "collision", "unfinished")},
        "vehicle": "sitl" if vehicle.sitl is not None else "sim",
        "timing": "lockstep" if lockstep else "real time",
        "lidar_turn_s": lidar_turn_s,
        "outcomes": outcomes,
        "health": episode_health(files.episodes),
        "mean_steps": round(sum(steps) / count, 1),
        "wall_s": round(time.monotonic() - started, 1),
        "exit_codes": codes,
        "folder": str(out),
        "served": None if serve is None else str(serve.folder),
        "recording": sorted(str(p) for p in files.recording.glob("*.mcap")),
    }


def _configure(
    files: StackFiles,
    policy: Path,
    hub: str,
    vehicle: _Vehicle,
    world: WorldConfig,
    *,
    lockstep: bool,
    serve: StackServe | None,
    lookahead: LookaheadSettings | None,
) -> None:
    """The daemons' settings files for this stack (`write_configs`)."""
    from qnav.simcar.car import SimCarSettings
    from qnav.tracking import fitted_proximity, room_of

    write_configs(
        files,
        policy,
        hub,
        vehicle.mavlink_port,
        world.robot_radius_m,
        bridge_values=vehicle.bridge_values,
        public_key=None if serve is None else serve.public_key,
        # In lockstep the world waits for the controller: a scan's age in wall time is the
        # stack's, not the world's, and a stop for a stale scan would restart the policy's
        # window mid-episode. The controller waits as long as the sim-car does.
        input_timeout_s=(
            SimCarSettings().lockstep_timeout_s + world.control_period_s if lockstep else 0.0
        ),
        lookahead=None if lookahead is None else room_of(world, lookahead),
        proximity=fitted_proximity(world),
    )


@dataclass
class _Vehicle:
    """The car the sim-car drives: the MAVLink test vehicle or ArduPilot Rover SITL."""

    mavlink_port: int
    """The bridge's MAVLink port on loopback (the test vehicle's)."""
    args: list[str]
    """The sim-car's options that name the car (and its lockstep and lidar)."""
    sitl: SitlProcess | None = None
    """The autopilot, with `--vehicle sitl`."""
    bridge_values: dict[str, Any] | None = None
    """The bridge's settings for SITL's serial ports."""


def _vehicle(
    files: StackFiles, lockstep: bool, sitl_binary: Path | None, lidar_turn_s: float
) -> _Vehicle:
    """The test vehicle (in lockstep, or real time), or SITL with `sitl_binary`."""
    mavlink_port = free_port(socket.SOCK_DGRAM)
    args = ["--vehicle-connection", f"udpin:127.0.0.1:{mavlink_port}"]
    if lockstep:
        args.append("--lockstep")
    if lidar_turn_s:
        if not lockstep:
            raise ConfigError("--lidar-turn-s needs lockstep (not --real-time, not --vehicle sitl)")
        args += ["--set", f"lidar_turn_s={lidar_turn_s!r}"]
    if sitl_binary is None:
        return _Vehicle(mavlink_port, args)
    from qnav.sitl import SITL_PARAMS, SKID_PARAMS, SitlProcess

    sitl = SitlProcess(
        sitl_binary, files.root / "sitl", [SITL_PARAMS, SKID_PARAMS], model="rover-skid"
    )
    return _Vehicle(
        mavlink_port,
        ["--firmware-connection", sitl.serial0],
        sitl,
        sitl_bridge_settings(sitl.serial1),
    )


def _start_daemons(
    daemons: Daemons, files: StackFiles, hub: str, record: bool, serve: StackServe | None
) -> None:
    """The recorder and the daemons first: they wait for the sim-car, which is the zenoh hub,
    so nothing the sim-car publishes is missed."""
    if record:
        daemons.start("recorder", "record", "--folder", str(files.recording), "--connect", hub)
    daemons.start("controller", "controller", "--config", str(files.controller_toml))
    daemons.start("bridge", "bridge", "--config", str(files.bridge_toml))
    if serve is not None:
        daemons.start(
            "server", "serve", str(serve.folder), "--key", str(serve.private_key),
            "--connect", hub, "--poll-s", str(serve.poll_s),
            "--announce-interval-s", str(serve.announce_interval_s),
        )  # fmt: skip


def _drive(
    daemons: Daemons, files: StackFiles, sim_car_args: list[str], episodes: int, progress: bool
) -> tuple[list[str], list[int]]:
    """The sim-car's episodes to their end: each one's outcome and steps, as it reports them,
    the other daemons checked alive after every line."""
    from tqdm import tqdm

    outcomes: list[str] = []
    steps: list[int] = []
    sim_car = daemons.start("sim-car", "sim-car", *sim_car_args, stdout=subprocess.PIPE)
    assert sim_car.stdout is not None
    with tqdm(total=episodes, desc="stack episodes", unit="ep", disable=not progress) as bar:
        for line in sim_car.stdout:
            if line.startswith("episode "):
                outcomes.append(line.split()[2].rstrip(","))
                steps.append(int(line.split()[3]))
                bar.update(1)
                bar.set_postfix(success=f"{outcomes.count('success') / len(outcomes):.2f}")
            daemons.check_alive()
    if sim_car.wait() != 0:
        tail = files.log("sim-car").read_text().strip().splitlines()[-5:]
        raise RuntimeError("sim-car failed:\n  " + "\n  ".join(tail))
    return outcomes, steps


def episode_health(episodes_log: Path) -> dict[str, int]:
    """The sim-car's per-period health figures (`simcar.car.EpisodeLog`) summed over its episode
    log: steps, and the periods the controller had not decided on in time (undecided), decided
    on another pose than the scan's (stale_pose), stopped on (stops), or whose command reached
    the car too late for lockstep (late)."""
    totals = {"steps": 0, "undecided": 0, "stale_pose": 0, "stops": 0, "late": 0}
    if not episodes_log.is_file():
        return totals
    for line in episodes_log.read_text().splitlines():
        entry = json.loads(line)
        totals["steps"] += int(entry["steps"])
        for name in ("undecided", "stale_pose", "stop", "late"):
            totals[name if name != "stop" else "stops"] += int(entry.get(f"{name}_steps", 0))
    return totals


@contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """Within the block SIGTERM and SIGINT interrupt (KeyboardInterrupt), so `run_stack` stops
    its daemons in order: by default SIGTERM ended the stack at once and left them running, and
    SIGINT did nothing where the stack inherited it ignored (started in the background by a
    non-interactive shell). Call from the main thread."""

    def interrupt(number: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    numbers = (signal.SIGTERM, signal.SIGINT)
    previous = [signal.signal(number, interrupt) for number in numbers]
    try:
        yield
    finally:
        for number, handler in zip(numbers, previous, strict=True):
            signal.signal(number, handler)


def stack_verb(args: argparse.Namespace) -> int:
    """`qnav stack`: the full stack, then the same episodes in process, side by side."""
    from qnav.tracking import lookahead_settings

    if not args.policy.is_file():
        raise ConfigError(f"--policy {args.policy} does not exist")
    lookahead = None if args.lookahead == "off" else lookahead_settings(args.lookahead)
    serve = None
    if args.serve_folder is not None or args.keys is not None:
        if args.serve_folder is None or args.keys is None:
            raise ConfigError("--serve-folder and --keys go together (docs/serve.md)")
        serve = StackServe(args.serve_folder, args.keys)
        serve.check()
    sitl_binary = _sitl_binary(args) if args.vehicle == "sitl" else None
    with sigterm_interrupts():
        result = run_stack(
            args.policy,
            args.out,
            scenario=args.scenario,
            episodes=args.episodes,
            record=not args.no_record,
            progress=not args.json,
            sitl_binary=sitl_binary,
            serve=serve,
            lockstep=not args.real_time,
            lookahead=lookahead,
            lidar_turn_s=args.lidar_turn_s,
        )
    result["in_process"] = in_process_outcomes(
        args.policy,
        result["scenario"],
        args.episodes,
        lookahead=lookahead,
        lidar_turn_s=args.lidar_turn_s,
    )
    result["gap"] = round(result["success"] - result["in_process"]["success"], 3)
    result["agreement"] = episode_agreement(
        args.policy,
        result["scenario"],
        args.out / "episodes.jsonl",
        lookahead=lookahead,
        lidar_turn_s=args.lidar_turn_s,
    )
    result["response"] = action_response(args.out / "episodes.jsonl", result["scenario"])
    print(json.dumps(result) if args.json else _report(result))
    return 0


def _sitl_binary(args: argparse.Namespace) -> Path:
    """The ardurover binary of `--vehicle sitl`; ConfigError where there is none, or where this
    network namespace reaches beyond loopback."""
    from qnav.sitl import SITL_ENV, network_is_isolated, sitl_binary_from_env

    sitl_binary: Path | None = args.sitl_binary or sitl_binary_from_env()
    if sitl_binary is None:
        raise ConfigError(f"--vehicle sitl needs --sitl-binary or {SITL_ENV} (docs/bridge.md)")
    if not network_is_isolated():
        # SITL serves unauthenticated TCP ports: only loopback may reach them.
        raise ConfigError(
            "--vehicle sitl runs only in a network namespace of its own (loopback only): "
            "`make stack-sitl`, or `unshare --net sh -c 'ip link set lo up && qnav stack ...'`"
        )
    return sitl_binary


def _report(result: dict[str, Any]) -> str:
    """`qnav stack`'s result as its lines: the stack, its health, the same episodes in process,
    and where its files are."""
    health, same = result["health"], result["in_process"]
    agreement, response = result["agreement"], result["response"]
    lines = [
        f"full stack ({result['vehicle']}, {result['timing']}), {result['scenario']}, "
        f"{result['episodes']} episodes ({result['wall_s']:.0f} s): success "
        f"{result['success']:.3f}, collision {result['collision']:.3f}, unfinished "
        f"{result['unfinished']:.3f}",
        f"per control period, of {health['steps']}: the controller had not decided on the scan "
        f"in time {health['undecided']}, decided on another pose {health['stale_pose']}, "
        f"stopped {health['stops']}; commands too late for lockstep {health['late']}",
        f"in process, same episodes: success {same['success']:.3f}, collision "
        f"{same['collision']:.3f}, unfinished {same['unfinished']:.3f}; "
        f"gap {result['gap']:+.3f}; mean steps {result['mean_steps']} in the stack, "
        f"{same['mean_steps']} in process",
        f"episode by episode, beside the policy in process on one stream as the controller "
        f"runs it: the same actions in {agreement['same_actions']} of "
        f"{agreement['episodes']}, the same outcome in {agreement['same_outcome']}",
        f"per control period: forward {response['forward_m_per_step']} m "
        f"(trained {response['trained_m_per_step']}), turn {response['turn_rad_per_step']} "
        f"rad (trained {response['trained_rad_per_step']}); by place in a run of one "
        f"action (1st, 2nd, 3rd, 4th+): forward {response['forward_m_by_run']} m, "
        f"turn {response['turn_rad_by_run']} rad; scan to command (median) "
        f"{response['scan_to_command_ms']} ms",
        f"configuration, logs and episode log in {result['folder']}",
    ]
    if result["recording"]:
        lines.append(f"recording: {', '.join(result['recording'])}")
    return "\n".join(lines)


def action_response(episodes_log: Path, scenario_name: str) -> dict[str, Any]:
    """How far the car moved per control period on each kind of action, from the sim-car's
    episode log, beside what the trained dynamics do (the action's velocity x the period):
    the firmware's speed and turn-rate response, lags and latency included. `*_by_run` splits
    the same by the period's place in a run of one action (1st, 2nd, 3rd, 4th and later): the
    lag after a change of action. `scan_to_command_ms`: the median time from a scan's
    publication to the command after it (the controller and zenoh), as the sim-car logged it."""
    import math

    from qnav.contracts.motion import action_velocities
    from qnav.sim.config import scenario as load_scenario

    world = load_scenario(scenario_name)
    period = world.control_period_s
    velocities = action_velocities(world.dynamics, period)
    runs = 4
    delays: list[float] = []
    forward: list[list[float]] = [[] for _ in range(runs)]
    turn: list[list[float]] = [[] for _ in range(runs)]
    for line in episodes_log.read_text().splitlines():
        entry = json.loads(line)
        poses, actions = entry["poses"], entry["actions"]
        delays += entry.get("command_delays_s", [])
        place = 0
        for i, action in enumerate(actions[: len(poses) - 1]):
            place = place + 1 if i > 0 and actions[i - 1] == action else 0
            if action < 0:
                continue
            (x0, y0, yaw0), (x1, y1, yaw1) = poses[i][:3], poses[i + 1][:3]
            linear, angular = velocities[action]
            slot = min(place, runs - 1)
            # Signed along what was asked, in units of the trained step's length.
            if linear != 0:
                moved = (x1 - x0) * math.cos(yaw0) + (y1 - y0) * math.sin(yaw0)
                forward[slot].append(moved / (linear * period))
            if angular != 0:
                turned = math.atan2(math.sin(yaw1 - yaw0), math.cos(yaw1 - yaw0))
                turn[slot].append(turned / (angular * period))
    trained_m = max(abs(v[0]) for v in velocities) * period
    trained_rad = max(abs(v[1]) for v in velocities) * period

    def mean(values: list[float], scale: float) -> float:
        return round(scale * sum(values) / max(len(values), 1), 3)

    all_forward = [v for slot in forward for v in slot]
    all_turn = [v for slot in turn for v in slot]
    return {
        "forward_m_per_step": mean(all_forward, trained_m),
        "turn_rad_per_step": mean(all_turn, trained_rad),
        "trained_m_per_step": round(trained_m, 3),
        "trained_rad_per_step": round(trained_rad, 3),
        "forward_steps": len(all_forward),
        "turn_steps": len(all_turn),
        "forward_m_by_run": [mean(slot, trained_m) for slot in forward],
        "turn_rad_by_run": [mean(slot, trained_rad) for slot in turn],
        "scan_to_command_ms": round(1000 * sorted(delays)[len(delays) // 2], 1) if delays else None,
    }


def _lookahead_tables(
    lookahead: LookaheadSettings | None, proximity: ProximitySettings | None
) -> dict[str, Any]:
    """The controller's [lookahead] and [proximity] tables: `lookahead` in its room (the square's
    side or the walls), and the proximity stop's field (`proximity`, or the default), as the
    in-process agent runs them (`file_agent`); None: the policy alone (the look ahead off, the
    proximity stop off)."""
    if lookahead is None:
        return {"lookahead": {"mode": "off"}, "proximity": {"enabled": False}}
    room: dict[str, Any] = (
        {"walls": [list(wall) for wall in lookahead.walls]}
        if lookahead.walls
        else {"room_size_m": lookahead.room_size_m}
    )
    field = {} if proximity is None else {"proximity": asdict(proximity)}
    return {"lookahead": {"mode": lookahead.mode} | room} | field


def in_process_outcomes(
    policy: Path,
    scenario_name: str,
    episodes: int,
    *,
    lookahead: LookaheadSettings | None = None,
    lidar_turn_s: float = 0.0,
) -> dict[str, Any]:
    """`qnav eval --lookahead MODE` of the policy file on the stack's episodes (the test
    protocol's first ones), with the stack's lidar (`lidar_turn_s`)."""
    from qnav.sim.config import scenario as load_scenario
    from qnav.sim.evaluate import EvalSettings, evaluate

    world = replace(load_scenario(scenario_name), lidar_turn_s=lidar_turn_s)
    result = evaluate(
        world,
        file_agent(policy, world, episodes, lookahead=lookahead),
        EvalSettings(episodes=episodes, num_worlds=episodes),
    )
    return {
        "success": float(result.success),
        "collision": float(result.collision),
        "unfinished": float(result.unfinished),
        "mean_steps": round(float(result.mean_steps), 1),
    }


def file_agent(
    policy: Path, world: WorldConfig, worlds: int, *, lookahead: LookaheadSettings | None
) -> Agent:
    """The policy file on one stream per world, as the controller runs it, with its look ahead
    and its proximity stop fitted to the world's robot (None: neither)."""
    from qnav.controller.perception import TrackerSettings
    from qnav.controller.policy import PolicyRuntime
    from qnav.sim.evaluate import StreamPolicyAgent
    from qnav.tracking import LookaheadAgent, fitted_proximity

    agent = StreamPolicyAgent(PolicyRuntime(policy, num_streams=worlds), worlds)
    if lookahead is None:
        return agent
    return LookaheadAgent(
        agent,
        world,
        worlds,
        tracker=TrackerSettings(),
        lookahead=lookahead,
        proximity=fitted_proximity(world),
    )


def episode_agreement(
    policy: Path,
    scenario_name: str,
    episodes_log: Path,
    *,
    lookahead: LookaheadSettings | None = None,
    lidar_turn_s: float = 0.0,
) -> dict[str, int]:
    """Each episode of the sim-car's log run again in process one at a time, the policy on one
    stream as the controller runs it: how many took the same action at every step
    (`same_actions`) and ended alike (`same_outcome`). In lockstep the stack should match every
    one; the batched `in_process_outcomes` can differ where an int8 file quantises its
    activations over the whole batch."""
    import numpy as np

    from qnav.contracts.motion import Outcome
    from qnav.sim.config import scenario as load_scenario
    from qnav.sim.evaluate import EvalSettings
    from qnav.sim.world import observe, reset, step

    test = EvalSettings()
    world = replace(
        load_scenario(scenario_name),
        max_episode_steps=test.max_episode_steps,
        lidar_turn_s=lidar_turn_s,
    )
    names = {Outcome.SUCCESS: "success", Outcome.COLLISION: "collision"}
    agent = file_agent(policy, world, 1, lookahead=lookahead)
    counts = {"episodes": 0, "same_actions": 0, "same_outcome": 0}
    for line in episodes_log.read_text().splitlines():
        entry = json.loads(line)
        state = reset(world, np.array([test.seed]), np.array([entry["episode"]]))
        observation = observe(world, state)
        agent.start(np.arange(1), np.array([entry["episode"]]))
        actions: list[int] = []
        while True:
            action = agent.act(observation)
            actions.append(int(action[0]))
            state, observation, transition = step(world, state, action)
            if transition.terminated[0] or transition.truncated[0]:
                break
        counts["episodes"] += 1
        counts["same_actions"] += actions == entry["actions"]
        ended = names.get(Outcome(int(transition.outcome[0])), "unfinished")
        counts["same_outcome"] += ended == entry["outcome"]
    return counts


def add_verbs(verbs: Verbs) -> None:
    """`qnav stack`: its options."""
    _add_stack(verbs)


def _add_stack(verbs: Verbs) -> None:
    """`qnav stack --policy FILE.onnx`."""
    parser = verb(
        verbs,
        stack_verb,
        "stack",
        help="the full stack as separate processes (sim-car, controller, bridge, recorder)",
    )
    parser.add_argument("--policy", type=Path, required=True, help="policy file (.onnx)")
    parser.add_argument("--scenario", help="world (default: the policy's training scenario)")
    parser.add_argument("--episodes", type=int, default=20, help="episodes (20)")
    lookahead_option(parser, "in the controller, and alike in the in-process comparison: ")
    parser.add_argument("--out", type=Path, default=Path("out/stack"), help="output folder")
    flag(parser, "--no-record", "do not record to MCAP")
    flag(parser, "--json", "print one JSON object")
    parser.add_argument(
        "--vehicle",
        choices=["sim", "sitl"],
        default="sim",
        help="the car: the MAVLink test vehicle (sim), or ArduPilot Rover SITL driven in GUIDED "
        "with the pose from the autopilot (sitl; loopback-only namespace, `make stack-sitl`)",
    )
    flag(
        parser,
        "--real-time",
        "the sim-car in real time: the car moves under whatever command it has while the "
        "next is decided (latency and load included); default: lockstep (`sim-car --lockstep`), "
        "the same episodes as in process. --vehicle sitl always runs in real time",
    )
    parser.add_argument(
        "--sitl-binary", type=Path, help="ardurover binary for --vehicle sitl ($ARDUPILOT_SITL)"
    )
    parser.add_argument(
        "--lidar-turn-s",
        type=float,
        default=0.0,
        metavar="S",
        help="a rotating lidar whose turn takes S seconds (0.1: 10 Hz): each beam cast from where "
        "the car and the obstacles were at its own time, sent with LaserScan's time_increment, "
        "and the same lidar in the in-process comparison (the world's lidar_turn_s; lockstep "
        "only; default 0: instantaneous scans)",
    )
    parser.add_argument(
        "--serve-folder",
        type=Path,
        metavar="DIR",
        help="also run `qnav serve DIR` on the stack's zenoh hub; the controller takes its "
        "policies (policy.source = server), --policy being its starting file (docs/serve.md)",
    )
    parser.add_argument(
        "--keys",
        type=Path,
        metavar="DIR",
        help="with --serve-folder: the key pair `qnav keys DIR` made (the server signs with its "
        "private key, the controller trusts its public key)",
    )
