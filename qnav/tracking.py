"""The controller's look ahead (`controller.lookahead`) on simulated cars: the in-process agent of
`qnav eval --lookahead` and `qnav stack`, and the timing of `qnav bench lookahead`.

The look ahead is the class a car's daemon runs (`controller.lookahead.Lookahead`), built here
for a simulated world's room, motion model and lidar, so the simulator's evaluation and the car
decide alike.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.errors import ConfigError
from qnav.contracts.lookahead import shielded_actions
from qnav.contracts.motion import action_velocities
from qnav.contracts.observation import LidarSpec
from qnav.controller.lookahead import Lookahead, LookaheadSettings, plans_of, risks_of
from qnav.controller.perception import TrackerSettings
from qnav.controller.proximity import (
    ProximitySettings,
    allowed_actions,
    blocked_parts,
    field_ranges,
    guarded_action,
)
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import WanderingGoToTarget, go_to_target
from qnav.sim.layouts import layouts_of
from qnav.sim.room import room_walls
from qnav.sim.world import BatchedWorld, Observation


def lidar_of(world: WorldConfig) -> LidarSpec:
    """`world`'s lidar; ConfigError naming the scenario when it has none to track with."""
    if world.lidar is None:
        raise ConfigError(f"scenario {world.name!r} has no lidar to track obstacles with")
    return world.lidar


def room_of(world: WorldConfig, settings: LookaheadSettings) -> LookaheadSettings:
    """`settings` with `world`'s room as a user measures it: the square's side, the walls of a
    polygon room as segments (`sim.room.room_walls`), or in a world of layouts (caves, BARN),
    which has no walls and lies outside the square, the box its obstacles move in
    (`Layouts.box`, the box round every layout's cylinders, starts and goals)."""
    if world.room.corners:
        walls = tuple(tuple(float(v) for v in wall) for wall in room_walls(world))
        return replace(settings, walls=walls)  # type: ignore[arg-type]
    layouts = layouts_of(world.layout)
    if layouts is not None:
        (x0, y0), (x1, y1) = layouts.box().tolist()
        box = ((x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0))
        return replace(settings, walls=box)
    return replace(settings, room_size_m=world.arena.size_m)


def world_lookahead(
    world: WorldConfig, settings: LookaheadSettings, tracker: TrackerSettings
) -> Lookahead:
    """The controller's look ahead as a car in `world` runs it: its room, motion model and
    lidar (what the policy file and the car's settings give the daemon)."""
    return Lookahead(
        room_of(world, settings),
        tracker,
        dynamics=world.dynamics,
        robot_radius_m=world.robot_radius_m,
        control_period_s=world.control_period_s,
        beam_angles_rad=lidar_of(world).beam_angles_rad(),
    )


def noisy(
    scans_m: NDArray[np.float32], sigma_m: float, random: np.random.Generator
) -> NDArray[np.float32]:
    """The scans with Gaussian range noise of `sigma_m` (unchanged without)."""
    if not sigma_m:
        return scans_m
    return (scans_m + random.normal(0.0, sigma_m, scans_m.shape)).astype(np.float32)


def lookahead_settings(mode: str) -> LookaheadSettings:
    """The look ahead of `--lookahead MODE`."""
    return LookaheadSettings(mode=mode)  # type: ignore[arg-type]


class QAgent(Protocol):
    """An agent that keeps the Q values of its last choice (`training.agent.TorchAgent`)."""

    last_q: NDArray[np.float32]

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None: ...

    def act(self, observation: Observation) -> NDArray[np.int64]: ...


class GoToTargetValues:
    """Blind go-to-target (`sim.evaluate.go_to_target`) as a policy to shield: its choice valued
    1, the others 0, so the shield keeps its choice unless that is too risky, and then takes the
    first of the least risky (`qnav eval --agent goto --lookahead shield`: what the shield and
    its forecast achieve without a learned policy)."""

    def __init__(self, num_worlds: int) -> None:
        self.last_q = np.zeros((num_worlds, NUM_ACTIONS), dtype=np.float32)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        """No memory to reset."""

    def act(self, observation: Observation) -> NDArray[np.int64]:
        action = go_to_target(observation.target_features())
        self.last_q = np.eye(NUM_ACTIONS, dtype=np.float32)[action]
        return action


class LookaheadAgent:
    """A learned policy with the controller's look ahead (`controller.lookahead`, one per world,
    as each car runs it), in `lookahead.mode`: "shield", each action's share of colliding
    continuations is forecast from the tracker's obstacles and the room's walls and the policy's
    best-valued action stands unless it is too risky (`lookahead.overrule_share`), then its
    best-valued among the safest; "plan", the planner on that state decides.
    With `proximity`, the controller's proximity stop then forbids motion into its safety field
    (`controller.proximity`), as the daemon applies it; the simulator has no stop, so where the
    field forbids every action (something inside the footprint: with the default footprint,
    the robot's radius, only a collision, which has ended the episode) the action stands and is
    counted in `proximity_stops`.
    """

    def __init__(
        self,
        inner: QAgent,
        world: WorldConfig,
        num_worlds: int,
        *,
        tracker: TrackerSettings,
        lookahead: LookaheadSettings,
        range_noise_m: float = 0.0,
        seed: int = 0,
        proximity: ProximitySettings | None = None,
    ) -> None:
        self.inner = inner
        self.world = world
        self.settings = room_of(world, lookahead)
        if self.settings.mode == "off":
            raise ConfigError("lookahead.mode = 'off': nothing to run beside the policy")
        self.cars = [world_lookahead(world, lookahead, tracker) for _ in range(num_worlds)]
        self.range_noise_m = range_noise_m
        self._noise = np.random.default_rng([seed, 31])
        self.steps = np.zeros(num_worlds, dtype=np.int64)
        self.overruled = 0
        """Decisions where the look ahead changed the policy's action."""
        self.decisions = 0
        """Decisions taken."""
        self.proximity = proximity if proximity is not None and proximity.enabled else None
        linear = [v for v, _ in action_velocities(world.dynamics, world.control_period_s)]
        self._linear_mps = np.array(linear)
        self.proximity_changes = 0
        """Decisions the proximity stop changed to another action."""
        self.proximity_stops = 0
        """Decisions where it forbade every action (the daemon would stop; here they stand)."""
        self.last_risks: NDArray[np.float64] | None = None
        """(N, A) the shield's risks of the last decision (None in plan mode)."""

    @property
    def overruled_share(self) -> float:
        """Share of the decisions so far where the look ahead changed the policy's action."""
        return self.overruled / max(self.decisions, 1)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.inner.start(worlds, episodes)
        for row in worlds.tolist():
            self.cars[row].restart()
        self.steps[worlds] = 0

    def act(self, observation: Observation) -> NDArray[np.int64]:
        chosen = self.inner.act(observation)
        assert observation.scan_m is not None  # the constructor checked the world has a lidar
        scans = noisy(observation.scan_m, self.range_noise_m, self._noise)
        times_s = self.steps * self.world.control_period_s
        turn_s, delays_s = self.world.lidar_turn_s, None
        if turn_s:  # a rotating lidar: its scan is stamped at the turn's start, as on the wire
            delays_s = turn_s / scans.shape[1] * np.arange(scans.shape[1])
        for row, car in enumerate(self.cars):
            now_s = float(times_s[row])
            car.observe(now_s, observation.pose[row], now_s - turn_s, scans[row], delays_s)
        targets = list(observation.target_xy)
        shares = None
        if self.settings.mode == "plan":
            action = plans_of(self.cars, targets)
        else:
            shares = risks_of(self.cars, targets)
            action = shielded_actions(
                self.inner.last_q, shares, self.settings.overrule_share, chosen
            )
        self.last_risks = shares
        self.overruled += int(np.sum(action != chosen))
        self.decisions += action.size
        self.steps += 1
        return action if self.proximity is None else self._guard(action, scans, shares)

    def _guard(
        self,
        action: NDArray[np.int64],
        scans: NDArray[np.float32],
        shares: NDArray[np.float64] | None,
    ) -> NDArray[np.int64]:
        """`action` as the controller's proximity stop leaves it, world by world."""
        assert self.proximity is not None
        angles = lidar_of(self.world).beam_angles_rad()
        guarded = action.copy()
        for row, scan in enumerate(scans):
            ranges = field_ranges(scan, 0.0, np.inf, below_min_is_no_return=False)
            blocked = blocked_parts(
                angles, ranges, self.proximity.footprint_m, self.proximity.travel_m
            )
            allowed = allowed_actions(self._linear_mps, blocked)
            choice = guarded_action(
                int(action[row]),
                allowed,
                self.inner.last_q[row],
                None if shares is None else shares[row],
                self.settings.overrule_share,
            )
            if choice is None:
                self.proximity_stops += 1
            elif choice != action[row]:
                self.proximity_changes += 1
                guarded[row] = choice
        return guarded


def fitted_proximity(world: WorldConfig) -> ProximitySettings:
    """The proximity stop's field fitted to `world`'s robot: footprint and travel one robot
    radius each, as the shipped defaults are in the paper's world (0.5 m). The 0.5 m field
    holds BARN's 0.3 m robot among the cylinders (docs/barn.md)."""
    return ProximitySettings(footprint_m=world.robot_radius_m, travel_m=world.robot_radius_m)


def shipped_agent(
    inner: QAgent, world: WorldConfig, num_worlds: int, mode: str = "shield", seed: int = 0
) -> LookaheadAgent:
    """The policy as the shipped controller runs it (`config/controller.toml`): the look ahead
    in `mode` with the default tracker and forecast, and the proximity stop below it, its field
    fitted to the world's robot (`fitted_proximity`)."""
    return LookaheadAgent(
        inner,
        world,
        num_worlds,
        tracker=TrackerSettings(),
        lookahead=lookahead_settings(mode),
        seed=seed,
        proximity=fitted_proximity(world),
    )


def time_lookahead(
    world: WorldConfig,
    decisions: int = 2000,
    seed: int = 1005,
    worlds: int = 20,
) -> dict[str, float]:
    """Wall time of the controller's look ahead per decision, one car at a time as the daemon
    runs it: the tracker's update, the shield's forecast and the plan, on a drive of go-to-target
    with held random actions by `worlds` cars; median and 99th percentile, milliseconds. Also
    the shield's forecast of all the cars at once, per car ("shield_batched"): what the lab's
    evaluations and labels pay per state."""
    tracker = TrackerSettings()

    def car(mode: Literal["shield", "plan"]) -> Lookahead:
        return world_lookahead(world, LookaheadSettings(mode=mode), tracker)

    pairs = [(car("shield"), car("plan")) for _ in range(worlds)]
    batched = BatchedWorld(world, worlds, seed=seed)
    observation = batched.reset(seed)
    driver = WanderingGoToTarget(worlds, 0.3, seed)
    times: dict[str, list[float]] = {"track": [], "shield": [], "plan": [], "shield_batched": []}
    while len(times["plan"]) < decisions:
        assert observation.scan_m is not None
        steps = batched.state.steps
        for row, (shield, planner) in enumerate(pairs):
            if steps[row] == 0:
                shield.restart()
                planner.restart()
            now = float(steps[row]) * world.control_period_s
            target = observation.target_xy[row]
            pose, scan = observation.pose[row], observation.scan_m[row]
            started = time.perf_counter()
            shield.observe(now, pose, now, scan)
            tracked = time.perf_counter()
            shield.risks(target)
            shielded = time.perf_counter()
            planner.observe(now, pose, now, scan)
            observed = time.perf_counter()
            planner.plan(target)
            planned = time.perf_counter()
            times["track"].append(tracked - started)
            times["shield"].append(shielded - tracked)
            times["plan"].append(planned - observed)
        shields = [shield for shield, _ in pairs]
        started = time.perf_counter()
        risks_of(shields, list(observation.target_xy))
        times["shield_batched"].append((time.perf_counter() - started) / len(shields))
        observation = batched.step(driver(observation.target_features())).observation
    report: dict[str, float] = {"decisions": float(len(times["plan"]))}
    for name, values in times.items():
        median, p99 = np.percentile(np.array(values) * 1e3, [50, 99])
        report[f"{name}_ms_p50"], report[f"{name}_ms_p99"] = float(median), float(p99)
    return report
