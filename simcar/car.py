"""The simulator plays the car: sensors out on zenoh, motion in over MAVLink.

`qnav sim-car` runs one simulated world in real time. Every control period it publishes what
the car's drivers would: the lidar as a `sensor_msgs/LaserScan` (the world's beams, over
[0, 2 pi) counter-clockwise from the heading) and the motion-capture pose as a
`geometry_msgs/PoseStamped`; at the start of each episode it publishes the target as a
`PoseStamped` on `goal_pose`. The robot moves only as the MAVLink test vehicle
(`simcar.mavlink_vehicle`) moves, driven by whatever reaches it over MAVLink (the firmware
bridge); the obstacles move as in the simulator. The episode's outcome is judged by the
simulator's own rules (`sim.world.step_outcome`: the world's reach radius), and the next
episode starts at once.

With `lockstep` (`qnav sim-car --lockstep`, as `qnav stack` runs it), the world waits for the
controller: each period it steps only once the controller's status names the period's scan and
the test vehicle has taken that decision's command over MAVLink, and then the car moves exactly
one control period under it (`MavlinkVehicle.advance`), so the episode is the in-process one
whatever the latency. Either way the episode log counts, per period, the decisions that came
too late, on another pose, or as stops (`EpisodeLog`).

With `firmware_connection` (`qnav sim-car --firmware-connection`), a real autopilot moves the
robot instead: its own pose estimate is the robot's pose (`simcar.firmware_vehicle`), as in
`qnav stack --vehicle sitl`.

Episode g has the layout of the test protocol's episode g (seed and episode index as in
`sim.evaluate`), so a run of the full stack can be compared with `qnav eval` of the same policy
file, episode by episode.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts import wire
from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import (
    IncrementDynamics,
    InertiaDynamics,
    Outcome,
    action_velocities,
    move_obstacles,
    step_velocity_lag,
)
from qnav.contracts.settings import check_range
from qnav.contracts.transport import StoppedError, ZenohSettings, open_session
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalSettings
from qnav.sim.render import EpisodeRecord
from qnav.sim.task import reward
from qnav.sim.world import RobotPath, WorldState, observe, obstacle_box, reset, step_outcome
from qnav.simcar.firmware_vehicle import FirmwareVehicle, FirmwareVehicleSettings
from qnav.simcar.mavlink_vehicle import MavlinkVehicle, MavlinkVehicleSettings

log = logging.getLogger("qnav.simcar.car")


@dataclass(frozen=True)
class SimCarSettings:
    """The simulated car: which world, how many episodes, and its two links."""

    SECTION = "sim_car"

    episodes: int = 50
    """Episodes to run before exiting."""
    seed: int = EvalSettings().seed
    """Layout seed (default: the test protocol's, so `qnav eval` runs the same episodes)."""
    first_episode: int = 0
    """Index of the first episode."""
    max_episode_steps: int = EvalSettings().max_episode_steps
    """Control periods before an episode counts as unfinished (paper: 500)."""
    vehicle_connection: str = "udpout:127.0.0.1:14550"
    """MAVLink connection of the simulated autopilot (default: to `qnav bridge`'s default)."""
    full_throttle_speed_mps: float = 1.0
    """Speed at full throttle (and turn rate in rad/s at full steering); set the bridge's
    speed_at_full_throttle_mps and turn_rate_at_full_steering_radps to the same."""
    increment_time_constant_s: float = 0.01
    """Velocity lag of the car in increment worlds: short, so that a command held for one
    control period moves the car by about one increment."""
    map_frame_id: str = "map"
    """frame_id of poses and targets."""
    lidar_frame_id: str = "laser"
    """frame_id of scans."""
    start_timeout_s: float = 30.0
    """Longest wait for the car to be armed before the first episode."""
    settle_s: float = 1.0
    """Pause after publishing a new target before the episode's clock starts."""
    rest_s: float = 0.0
    """After an episode, the car stays where it ended this long, its pose and scan still
    published every control period, before the next target: the controller sees the target
    reached and stops the car, as a real car at rest between two missions (the stop at which a
    delivered policy is swapped in, docs/serve.md). 0: the next target at once."""
    firmware_connection: str = ""
    """A real autopilot's MAVLink port (e.g. SITL's SERIAL0, tcp:127.0.0.1:5760): its own pose
    estimate moves the robot (`simcar.firmware_vehicle`) instead of the test vehicle; empty: the
    test vehicle on `vehicle_connection`."""
    rest_speed_mps: float = 0.05
    """With a firmware vehicle: an episode starts only once the vehicle is slower than this."""
    rest_timeout_s: float = 10.0
    """With a firmware vehicle: the longest wait for rest before an episode (then it starts
    anyway, and the log says so)."""
    lockstep: bool = False
    """Step the world only once the command decided on the period's scan has reached the test
    vehicle (the controller's status names the scan it decided on; the vehicle has taken that
    command over MAVLink), then move the car exactly one control period under it: the episodes
    of the in-process evaluation, whatever the decision's latency and the machine's load. The
    scans still leave at most once per control period. False: real time, the car moving under
    whatever command it has, latency included. Test vehicle only."""
    lockstep_timeout_s: float = 2.0
    """In lockstep, the longest wait for a period's command; then the world steps anyway and
    the period counts in `EpisodeLog.late_steps`."""

    def __post_init__(self) -> None:
        check_range(self, "episodes", self.episodes, 1, 10_000_000)
        check_range(self, "max_episode_steps", self.max_episode_steps, 1, 10_000_000)
        check_range(
            self, "full_throttle_speed_mps", self.full_throttle_speed_mps, 0, 20, exclusive_low=True
        )
        check_range(self, "settle_s", self.settle_s, 0, 60)
        check_range(self, "rest_s", self.rest_s, 0, 60)
        check_range(self, "rest_speed_mps", self.rest_speed_mps, 0, 10, exclusive_low=True)
        check_range(self, "rest_timeout_s", self.rest_timeout_s, 0, 600)
        check_range(self, "lockstep_timeout_s", self.lockstep_timeout_s, 0, 600, exclusive_low=True)
        if self.lockstep and self.firmware_connection:
            raise ConfigError(
                "lockstep = true needs the test vehicle: a firmware vehicle (firmware_connection) "
                "moves in its own real time"
            )


@dataclass
class EpisodeLog:
    """One episode as the simulated car saw it."""

    episode: int
    """Episode index (the test protocol's layout)."""
    outcome: str
    """success, collision or unfinished."""
    steps: int
    """Control periods it lasted."""
    poses: list[list[float]] = field(default_factory=list)
    """Robot pose at each period."""
    obstacles: list[list[list[float]]] = field(default_factory=list)
    """Obstacle centres at each period."""
    target: list[float] = field(default_factory=list)
    """Target position."""
    actions: list[int] = field(default_factory=list)
    """The action each period's command corresponds to (-1: stop)."""
    command_delays_s: list[float] = field(default_factory=list)
    """Per period, from publishing the scan to the arrival of a command after it (the
    controller's decision and zenoh both ways); periods without one are left out."""
    undecided_steps: int = 0
    """Periods whose scan the controller had not decided on (no status naming it) by the time
    the world stepped: the car moved on an older decision, and the policy's window missed or
    will take late a frame that in process it takes on time."""
    stale_pose_steps: int = 0
    """Periods whose decision used another pose than the one published with its scan (the
    status's target distance differs from the scan's pose's by more than a millimetre)."""
    stop_steps: int = 0
    """Periods in which the controller stopped the car (a safety rule applied, e.g.
    `scan_stale`, on the scan or before the next; each stop also restarts the policy's
    window)."""
    late_steps: int = 0
    """In lockstep: periods whose command did not reach the car within `lockstep_timeout_s`."""


class Decision(NamedTuple):
    """What the controller's status says it decided on one scan."""

    scan_stamp_s: float
    """Header stamp of the scan it decided on."""
    reason: str
    """Why the command is what it is (`policy`, or the stop's rule)."""
    linear_mps: float
    """The command's forward speed."""
    angular_radps: float
    """The command's turn rate."""
    target_distance_m: float | None
    """Distance from the pose it used to the target."""


STAMP_MATCH_S = 1e-4
"""A status names a scan when its scan stamp is this close to the scan's (the stamp crosses the
wire as seconds and nanoseconds; scans are a control period apart)."""

POSE_MATCH_M = 1e-3
"""A decision used the scan's own pose when its target distance is this close to the pose's."""

COMMAND_MATCH = 0.01
"""The car has taken a command when its commanded velocities are this close to it (m/s, rad/s;
the bridge's RC overrides are quantised to 1 us of PWM, 0.0025 of full travel)."""


LOCKSTEP_EPISODE_S = 1000.0
"""In lockstep, poses and scans are stamped with the simulator's clock, which the world's steps
advance (not the wall clock, which the waits for commands stretch): episode i starts at
(i + 1) * this many seconds, so stamps stay unique, and the controller's obstacle tracker sees
the periods the world really took."""

LOCKSTEP_INCREMENT_TIME_CONSTANT_S = 1e-6
"""The car's lag in increment worlds in lockstep: a period's move falls short of the increment
by the change of velocity times this (a micrometre)."""


def decision_of(report: dict[str, Any]) -> Decision | None:
    """The decision a controller status reports (None: it names no scan); KeyError, TypeError
    or ValueError if it is not a status."""
    stamp = report["scan_stamp_s"]
    if stamp is None:
        return None
    distance = report["target_distance_m"]
    command = report["command"]
    return Decision(
        float(stamp),
        str(report["reason"]),
        float(command["linear_mps"]),
        float(command["angular_radps"]),
        None if distance is None else float(distance),
    )


def vehicle_dynamics(world: WorldConfig, settings: SimCarSettings) -> InertiaDynamics:
    """The car's motion model: the world's lags, with full travel at `full_throttle_speed_mps`.

    In increment worlds the lag is short, so a command held for one control period moves the car
    about one increment, as the simulator's increment dynamics do. In lockstep, where the car
    moves one whole period per command, the lag is `LOCKSTEP_INCREMENT_TIME_CONSTANT_S`: the
    increment itself to a micrometre (with 0.01 s each change of action fell 5-10 % short, and
    measured in walls-increment, a left-right flip-flop ran an episode to 500 steps that takes
    20 in process).
    """
    full = settings.full_throttle_speed_mps
    if isinstance(world.dynamics, IncrementDynamics):
        if settings.lockstep:
            tau, dt = LOCKSTEP_INCREMENT_TIME_CONSTANT_S, world.control_period_s
        else:
            tau = settings.increment_time_constant_s
            dt = min(world.control_period_s, tau)
        return InertiaDynamics(
            max_speed_mps=full,
            max_turn_rate_radps=full,
            linear_time_constant_s=tau,
            angular_time_constant_s=tau,
            physics_dt_s=dt,
        )
    return replace(world.dynamics, max_speed_mps=full, max_turn_rate_radps=full)


def scan_message(
    ranges_m: NDArray[np.float32],
    stamp_s: float,
    frame_id: str,
    max_range_m: float,
    turn_s: float = 0.0,
) -> bytes:
    """The world's scan as a LaserScan: beam i at i * 2 pi / B, counter-clockwise, taken
    i * turn_s / B after the stamp (time_increment); no return is +inf, as ROS drivers report it
    (REP 117)."""
    beams = ranges_m.shape[0]
    return wire.encode_scan_msg(
        wire.Scan(
            stamp_s=stamp_s,
            frame_id=frame_id,
            angle_min_rad=0.0,
            angle_increment_rad=2 * math.pi / beams,
            range_min_m=0.0,
            range_max_m=max_range_m,
            ranges_m=ranges_m.astype(np.float32),
            time_increment_s=turn_s / beams,
        )
    )


def drive(vehicle: MavlinkVehicle, period_s: float) -> RobotPath:
    """Lockstep: move the test vehicle one period (`advance`); returns the path it took (poses
    (1, K, 3) at its physics steps), for a rotating lidar (`sim.world.rotating_scans`). The
    steps between are the vehicle's own motion model run on a copy of its state, so the car
    itself moves exactly as without a path (an ulp can decide a near-tie)."""
    params = vehicle.settings.dynamics
    steps = max(1, round(period_s / params.physics_dt_s))
    speed_mps, rate_radps = vehicle.targets()
    pose, velocity = np.array([vehicle.pose()]), np.array([vehicle.velocity()])
    path = [pose[0]]
    for _ in range(steps - 1):
        pose, velocity = step_velocity_lag(
            pose,
            velocity,
            np.array([speed_mps]),
            np.array([rate_radps]),
            params=params,
            period_s=period_s / steps,
        )
        path.append(pose[0])
    vehicle.advance(period_s)
    path.append(np.array(vehicle.pose()))
    return period_s * (np.arange(steps + 1) / steps - 1.0), np.array(path)[None]


class SimCar:
    """One world in real time, its robot moved by the MAVLink test vehicle."""

    def __init__(self, world: WorldConfig, settings: SimCarSettings, zenoh: ZenohSettings) -> None:
        self.world = replace(world, max_episode_steps=settings.max_episode_steps)
        self.settings = settings
        if world.lidar_turn_s and not settings.lockstep:
            raise ConfigError(
                "the world's lidar_turn_s needs the sim-car in lockstep (lockstep = true): the "
                "car's path during a turn is known only when the sim-car moves it"
            )
        self.zenoh = zenoh
        self.vehicle: MavlinkVehicle | FirmwareVehicle
        if settings.firmware_connection:
            self.vehicle = FirmwareVehicle(
                FirmwareVehicleSettings(connection=settings.firmware_connection)
            )
        else:
            self.vehicle = MavlinkVehicle(
                MavlinkVehicleSettings(
                    connection=settings.vehicle_connection,
                    dynamics=vehicle_dynamics(world, settings),
                    require_position_for_guided=False,
                    external_physics=settings.lockstep,
                )
            )
        self.episodes: list[EpisodeLog] = []
        self._velocities = np.array(action_velocities(world.dynamics, world.control_period_s))
        self._last_command: wire.Twist2D | None = None
        self._episode_start_s = 0.0
        self._command_arrival_s = -math.inf
        self._decisions: deque[Decision] = deque(maxlen=32)
        """The newest decisions the controller's status reported (under `_decided`)."""
        self._decided = threading.Condition()
        self._controller_heard = False
        """A controller status has arrived (under `_decided`): the controller listens."""

    def action_of(self, command: wire.Twist2D | None) -> int:
        """The action whose velocity the command is (-1 for a stop or none)."""
        if command is None or (command.linear_mps == 0 and command.angular_radps == 0):
            return -1
        gap = np.abs(self._velocities - [command.linear_mps, command.angular_radps]).sum(axis=1)
        return int(np.argmin(gap))

    def run(self, stop: threading.Event, progress: Any = None) -> list[EpisodeLog]:
        """Run the episodes (or until `stop`, which also ends the waits for the car's link and
        for zenoh); returns their logs."""
        try:
            self._start_vehicle(stop)
        except StoppedError:
            return self.episodes
        try:
            with open_session(self.zenoh, stop) as session:
                self._run_episodes(session, stop, progress)
        except StoppedError:
            pass  # stopped while waiting for zenoh
        finally:
            self.vehicle.close()
        return self.episodes

    def _start_vehicle(self, stop: threading.Event) -> None:
        """Start the car's link; an autopilot's port may open late (StoppedError on `stop`)."""
        if isinstance(self.vehicle, FirmwareVehicle):
            self.vehicle.start(stop=stop)
        else:
            self.vehicle.start()

    def _run_episodes(self, session: Any, stop: threading.Event, progress: Any) -> None:
        settings = self.settings
        namespace = self.zenoh.namespace
        publish = {
            topic.name: session.declare_publisher(wire.key(topic, namespace))
            for topic in (wire.SCAN, wire.POSE, wire.TARGET_POSE)
        }

        def on_command(sample: Any) -> None:
            with contextlib.suppress(wire.WireError):
                self._last_command = wire.decode_twist_msg(bytes(sample.payload.to_bytes()))
                self._command_arrival_s = time.monotonic()

        def on_status(sample: Any) -> None:
            with contextlib.suppress(wire.WireError, KeyError, TypeError, ValueError):
                report = wire.decode_json_msg(bytes(sample.payload.to_bytes()))
                decision = decision_of(report)
                with self._decided:
                    self._controller_heard = True
                    if decision is not None:
                        self._decisions.append(decision)
                    self._decided.notify_all()

        commands = session.declare_subscriber(wire.key(wire.COMMAND, namespace), on_command)
        statuses = session.declare_subscriber(
            wire.key(wire.CONTROLLER_STATUS, namespace), on_status
        )
        log.info("zenoh joined: waiting for the car to be armed")
        self._wait_until_armed(stop)
        self._wait_for_controller(stop)
        for index in range(settings.first_episode, settings.first_episode + settings.episodes):
            if stop.is_set():
                break
            log_entry = self._episode(index, publish, stop)
            if log_entry is None:  # interrupted: an episode cut short is not an outcome
                break
            self.episodes.append(log_entry)
            log.info("episode %d: %s after %d steps", index, log_entry.outcome, log_entry.steps)
            if progress is not None:
                progress(log_entry)
        commands.undeclare()
        statuses.undeclare()

    def _wait_until_armed(self, stop: threading.Event) -> None:
        deadline = time.monotonic() + self.settings.start_timeout_s
        while not self.vehicle.armed and not stop.is_set():
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"the car was not armed within {self.settings.start_timeout_s} s: is the "
                    f"bridge connected to {self.settings.vehicle_connection} with "
                    "vehicle.arm_on_connect = true?"
                )
            time.sleep(0.05)

    def _wait_for_controller(self, stop: threading.Event) -> None:
        """The first target goes out once the controller listens (its first status: it
        publishes one every period while stopped); a target published before it subscribed
        would never reach it (measured: a loaded machine's controller started late, missed the
        first episode's target and stood still through it)."""
        timeout = self.settings.start_timeout_s
        with self._decided:
            heard = self._decided.wait_for(lambda: self._controller_heard or stop.is_set(), timeout)
        if not heard:
            log.warning("no controller status within %g s: starting anyway", timeout)

    def _episode(
        self, index: int, publish: dict[str, Any], stop: threading.Event
    ) -> EpisodeLog | None:
        world, settings = self.world, self.settings
        state = reset(world, np.array([settings.seed]), np.array([index]))
        self._episode_start_s = (index + 1) * LOCKSTEP_EPISODE_S
        self._wait_for_rest(index)
        self.vehicle.set_pose(*state.pose[0])
        entry = EpisodeLog(index, "unfinished", 0, target=state.target_xy[0].tolist())
        # The target and the pose only: a scan now would be decided on, and that frame, taken
        # before the settling pause, would stay in the policy's window unless a stop for a
        # stale scan happened to restart it (measured: in lockstep, whose controller waits
        # longer, it changed a near-tie 23 steps later). The first scan is the first period's.
        self._publish(state, publish, target=True, with_scan=False)
        stop.wait(settings.settle_s)
        self._wait_for_rest(index)
        self.vehicle.set_pose(*state.pose[0])  # in case a late command moved it while settling
        period = world.control_period_s
        deadline = time.monotonic()
        self._record(state, entry)
        published_s = time.monotonic()
        stamp = self._publish(state, publish)
        distance = np.linalg.norm(state.target_xy - state.pose[:, :2], axis=1)
        while not stop.is_set():
            deadline += period
            if settings.lockstep:
                if not self._await_command(stamp, published_s + settings.lockstep_timeout_s, stop):
                    entry.late_steps += 1
                stop.wait(max(0.0, deadline - time.monotonic()))
                # A late command delays the next scan; it does not shorten the period after.
                deadline = max(deadline, time.monotonic())
            else:
                stop.wait(max(0.0, deadline - time.monotonic()))
            decisions = self._decisions_on(stamp)
            decision = next(iter(decisions), None)
            note_decision(entry, decisions, float(distance[0]))
            if self._command_arrival_s > published_s:
                entry.command_delays_s.append(self._command_arrival_s - published_s)
            command = self._last_command
            if settings.lockstep and decision is not None:
                command = wire.Twist2D(decision.linear_mps, decision.angular_radps)
            entry.actions.append(self.action_of(command))
            path = None  # the car's path within the period: only a rotating lidar needs it
            if settings.lockstep and isinstance(self.vehicle, MavlinkVehicle):
                if world.lidar_turn_s:
                    path = drive(self.vehicle, period)
                else:
                    self.vehicle.advance(period)
            state = self._advance(state)
            self._record(state, entry)
            observation = observe(world, state, path)
            distance = np.linalg.norm(state.target_xy - state.pose[:, :2], axis=1)
            result = int(step_outcome(world, distance, observation.clearance_m)[0])
            entry.steps = int(state.steps[0])
            if result != Outcome.RUNNING:
                entry.outcome = "success" if result == Outcome.SUCCESS else "collision"
                break
            if entry.steps >= world.max_episode_steps:
                break
            published_s = time.monotonic()
            stamp = self._publish(state, publish, observation_scan=observation.scan_m)
        self._rest(state, publish, stop)
        return None if stop.is_set() else entry

    def _decisions_on(self, stamp_s: float) -> list[Decision]:
        """The controller's outputs on the scan stamped `stamp_s` reported so far, first first
        (its decision on the scan, then any stop its periodic safety check made before the
        next scan)."""
        with self._decided:
            return [d for d in self._decisions if abs(d.scan_stamp_s - stamp_s) < STAMP_MATCH_S]

    def _decision_for(self, stamp_s: float) -> Decision | None:
        """The controller's first decision on the scan stamped `stamp_s`, if reported yet."""
        return next(iter(self._decisions_on(stamp_s)), None)

    def _await_command(self, stamp_s: float, until_s: float, stop: threading.Event) -> bool:
        """Lockstep: wait until the controller has decided on the scan stamped `stamp_s` and
        the car has taken that command over MAVLink (False: not by `until_s`)."""
        with self._decided:
            self._decided.wait_for(
                lambda: stop.is_set() or self._decision_for(stamp_s) is not None,
                max(0.0, until_s - time.monotonic()),
            )
        decision = self._decision_for(stamp_s)
        if decision is None or not isinstance(self.vehicle, MavlinkVehicle):
            return False
        return self.vehicle.wait_for_targets(
            decision.linear_mps,
            decision.angular_radps,
            COMMAND_MATCH,
            max(0.0, until_s - time.monotonic()),
        )

    def _rest(self, state: WorldState, publish: dict[str, Any], stop: threading.Event) -> None:
        """`rest_s` of control periods at the episode's end: the car's own pose and the scan
        there, as it comes to a stop under the controller's commands."""
        period = self.world.control_period_s
        deadline = time.monotonic()
        end = deadline + self.settings.rest_s
        while self.settings.rest_s > 0 and not stop.is_set() and deadline < end:
            self._publish(state._replace(pose=np.array([self.vehicle.pose()])), publish)
            deadline += period
            stop.wait(max(0.0, deadline - time.monotonic()))

    def _wait_for_rest(self, index: int) -> None:
        """A firmware vehicle keeps the speed it had: the episode starts once it is at rest."""
        vehicle, settings = self.vehicle, self.settings
        if not isinstance(vehicle, FirmwareVehicle):
            return
        if not vehicle.wait_for_rest(settings.rest_speed_mps, settings.rest_timeout_s):
            log.warning(
                "episode %d starts at %.2f m/s: not at rest within %g s (rest_timeout_s)",
                index,
                vehicle.speed_mps(),
                settings.rest_timeout_s,
            )

    def _advance(self, state: WorldState) -> WorldState:
        world = self.world
        low, high = obstacle_box(world, state.layout)
        obstacle_xy, obstacle_velocity = move_obstacles(
            state.obstacle_xy,
            state.obstacle_velocity,
            world.obstacles.radius_m,
            high - low,
            world.control_period_s,
            origin_m=low,
        )
        return state._replace(
            pose=np.array([self.vehicle.pose()]),
            obstacle_xy=obstacle_xy,
            obstacle_velocity=obstacle_velocity,
            steps=state.steps + 1,
        )

    def _record(self, state: WorldState, entry: EpisodeLog) -> None:
        entry.poses.append(state.pose[0].tolist())
        entry.obstacles.append(state.obstacle_xy[0].tolist())

    def _publish(
        self,
        state: WorldState,
        publish: dict[str, Any],
        *,
        target: bool = False,
        with_scan: bool = True,
        observation_scan: NDArray[np.float32] | None = None,
    ) -> float:
        """Publish the pose (and the target) and the scan (`observation_scan`, else the world's
        around the car standing still); returns the scan's stamp: the wall clock, or in lockstep
        the simulator's clock (`LOCKSTEP_EPISODE_S`), as the pose's, or with a rotating lidar
        (the world's `lidar_turn_s`) the start of its turn, which ends at the pose's stamp."""
        settings = self.settings
        stamp = time.time()
        if settings.lockstep:
            stamp = self._episode_start_s + float(state.steps[0]) * self.world.control_period_s
        x, y, yaw = state.pose[0]
        if target:
            tx, ty = state.target_xy[0]
            publish[wire.TARGET_POSE.name].put(
                wire.encode_pose_msg(wire.Pose2D(stamp, settings.map_frame_id, tx, ty))
            )
        publish[wire.POSE.name].put(
            wire.encode_pose_msg(wire.Pose2D(stamp, settings.map_frame_id, x, y, yaw))
        )
        turn_s = self.world.lidar_turn_s
        scan_stamp = stamp - turn_s
        if self.world.lidar is not None and with_scan:
            scan = observation_scan
            if scan is None:
                scan = observe(self.world, state).scan_m
            assert scan is not None
            publish[wire.SCAN.name].put(
                scan_message(
                    scan[0],
                    scan_stamp,
                    settings.lidar_frame_id,
                    self.world.lidar.max_range_m,
                    turn_s,
                )
            )
        return scan_stamp


def note_decision(entry: EpisodeLog, decisions: list[Decision], distance_m: float) -> None:
    """Count a period's outputs on its scan (`decisions`, first first) in the episode's health
    figures: none yet, a stop among them, or a decision on another pose than the scan's
    (`distance_m`: the scan's pose to the target)."""
    if not decisions:
        entry.undecided_steps += 1
        return
    decision = decisions[0]
    if any(d.reason != "policy" for d in decisions):
        entry.stop_steps += 1
    elif decision.target_distance_m is None or (
        abs(decision.target_distance_m - distance_m) > POSE_MATCH_M
    ):
        entry.stale_pose_steps += 1


def episode_record(world: WorldConfig, entry: EpisodeLog) -> EpisodeRecord:
    """A logged episode in the form `sim.render` draws."""
    poses = np.array(entry.poses)
    obstacles = np.array(entry.obstacles).reshape(len(entry.poses), world.obstacles.count, 2)
    outcome_value = {"success": Outcome.SUCCESS, "collision": Outcome.COLLISION}.get(
        entry.outcome, Outcome.RUNNING
    )
    distance = np.linalg.norm(poses[1:, :2] - np.array(entry.target), axis=1)
    return EpisodeRecord(
        config=world,
        poses=poses,
        obstacle_xy=obstacles,
        target_xy=np.array(entry.target),
        scans=None,
        actions=np.maximum(np.array(entry.actions, dtype=np.int64), 0),
        outcome=outcome_value,
        rewards=reward(
            distance, np.full(distance.shape, np.inf), world.robot_radius_m, world.reward
        ),
    )


def summary(episodes: list[EpisodeLog]) -> dict[str, float]:
    """Fractions by outcome, as `qnav eval --json` prints them."""
    count = max(len(episodes), 1)
    return {
        "success": sum(e.outcome == "success" for e in episodes) / count,
        "collision": sum(e.outcome == "collision" for e in episodes) / count,
        "unfinished": sum(e.outcome == "unfinished" for e in episodes) / count,
        "episodes": len(episodes),
    }


def write_log(episodes: list[EpisodeLog], path: Path) -> None:
    """The episodes as JSON lines (one object per episode)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as out:
        for entry in episodes:
            out.write(json.dumps(entry.__dict__) + "\n")
