"""World settings: every number of the paper's world, and a named setting for each gap it leaves.

The paper's own values are the defaults wherever it gives one. Values it does not give were
chosen as a roboticist would and calibrated so that a uniformly random agent reproduces the
paper's Random rows (docs/simulator.md lists each choice and why).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import Dynamics, IncrementDynamics, InertiaDynamics
from qnav.contracts.observation import LidarSpec
from qnav.contracts.settings import check_range, load_toml, parse_assignments, with_overrides

Wall = Literal["south", "east", "north", "west"]
WALLS: tuple[Wall, ...] = ("south", "east", "north", "west")


@dataclass(frozen=True)
class Opening:
    """A gap in one of the arena's four walls."""

    SECTION = "arena.openings"

    wall: Wall
    """Which wall: south (y = 0), east (x = size), north (y = size) or west (x = 0)."""
    centre_m: float
    """Position of the gap's centre along the wall, from the wall's west or south end."""
    width_m: float
    """Width of the gap."""


@dataclass(frozen=True)
class ArenaConfig:
    """The square room: walls all round, with a few small openings."""

    SECTION = "arena"

    size_m: float = 10.0
    """Side of the square arena (paper: 10 x 10 m)."""
    openings: tuple[Opening, ...] = (
        Opening("south", 3.0, 0.8),
        Opening("east", 6.5, 0.8),
        Opening("north", 7.0, 0.8),
        Opening("west", 3.5, 0.8),
    )
    """Gaps in the walls (paper: "few small openings"). Narrower than the robot, so lidar rays
    escape through them but the robot cannot; obstacles bounce off them as off the wall."""

    def __post_init__(self) -> None:
        check_range(self, "size_m", self.size_m, 1.0, 1000.0)
        for opening in self.openings:
            if opening.wall not in WALLS:
                raise ConfigError(f"arena.openings wall {opening.wall!r}: choose one of {WALLS}")
            half = opening.width_m / 2
            check_range(opening, "width_m", opening.width_m, 0.0, self.size_m, exclusive_low=True)
            check_range(
                opening,
                "centre_m",
                opening.centre_m,
                half,
                self.size_m - half,
                why="the opening must lie within its wall",
            )


@dataclass(frozen=True)
class ObstacleConfig:
    """Spheres moving in straight lines at constant speed, bouncing off the walls."""

    SECTION = "obstacles"

    count: int = 0
    """Number of moving obstacles (paper: 0 or 5)."""
    radius_m: float = 0.2
    """Sphere radius; the lidar plane cuts it at its centre (paper: not given; 0.2 m lets the
    oracle reach the paper's best seeds, docs/simulator.md)."""
    speed_mean_mps: float = 1.0
    """Mean of the speed's normal distribution (paper: 1.0 m/s)."""
    speed_std_mps: float = 0.3
    """Standard deviation of the speed (paper: 0.3 m/s)."""
    speed_min_mps: float = 0.5
    """Lower truncation of the speed (paper: 0.5 m/s)."""
    speed_max_mps: float = 1.5
    """Upper truncation of the speed (paper: 1.5 m/s)."""
    radius_max_m: float = 0.0
    """Each obstacle's radius drawn uniformly from [radius_m, radius_max_m] (a box's half sides
    each so drawn); 0: every obstacle of radius_m (the paper's)."""
    box_share: float = 0.0
    """Share of the obstacles that are boxes (rectangles turned to their heading), not
    cylinders (`sim.room`; 0: none, the paper's)."""
    legs_share: float = 0.0
    """Share of the obstacles that are a walking person's two legs (two 6 cm circles side by
    side, swinging as they walk: `sim.room.LEG_RADIUS_M`), not cylinders (0: none)."""
    heading_walk_rad: float = 0.0
    """Standard deviation of the random change of each obstacle's heading every control period
    (0: straight lines, the paper's)."""
    speed_walk_mps: float = 0.0
    """Standard deviation of the random change of each obstacle's walking speed every control
    period, kept within [speed_min_mps, speed_max_mps] (0: constant speed, the paper's)."""
    stop_probability: float = 0.0
    """Chance each control period that a walking obstacle stops (0: none stops, the paper's)."""
    start_probability: float = 0.2
    """Chance each control period that a stopped obstacle walks on (used only where
    stop_probability is set)."""

    def __post_init__(self) -> None:
        check_range(self, "count", self.count, 0, 1000)
        check_range(self, "radius_m", self.radius_m, 0.0, 100.0, exclusive_low=True)
        if self.radius_max_m:
            check_range(
                self,
                "radius_max_m",
                self.radius_max_m,
                self.radius_m,
                100.0,
                why="must be at least radius_m, or 0",
            )
        check_range(self, "box_share", self.box_share, 0.0, 1.0)
        check_range(
            self, "legs_share", self.legs_share, 0.0, 1.0 - self.box_share, why="with box_share"
        )
        check_range(self, "heading_walk_rad", self.heading_walk_rad, 0.0, 10.0)
        check_range(self, "speed_walk_mps", self.speed_walk_mps, 0.0, 100.0)
        check_range(self, "stop_probability", self.stop_probability, 0.0, 1.0)
        check_range(self, "start_probability", self.start_probability, 0.0, 1.0)
        check_range(self, "speed_std_mps", self.speed_std_mps, 0.0, 100.0)
        check_range(self, "speed_min_mps", self.speed_min_mps, 0.0, 100.0)
        check_range(
            self,
            "speed_max_mps",
            self.speed_max_mps,
            self.speed_min_mps,
            100.0,
            why="must be at least speed_min_mps",
        )
        check_range(
            self,
            "speed_mean_mps",
            self.speed_mean_mps,
            self.speed_min_mps,
            self.speed_max_mps,
            why="the mean must lie between the truncation limits",
        )

    @property
    def walks(self) -> bool:
        """Whether the obstacles turn, change speed or stop (a random walk each period)."""
        return bool(self.heading_walk_rad or self.speed_walk_mps or self.stop_probability)

    @property
    def shaped(self) -> bool:
        """Whether the obstacles are other than cylinders of one radius."""
        return bool(self.radius_max_m or self.box_share or self.legs_share)

    @property
    def largest_radius_m(self) -> float:
        """The largest radius an obstacle may be drawn with."""
        return max(self.radius_m, self.radius_max_m)


@dataclass(frozen=True)
class SensorConfig:
    """What a real lidar and motion capture add to the exact world's readings: all off (the
    paper's exact sensors) unless set (`sim.sensor`)."""

    SECTION = "sensor"

    lidar_readings: int = 0
    """Readings of the physical lidar per turn, resampled to the policy's `lidar.num_beams` by
    the controller's rule (each beam the nearest reading its sector overlaps:
    docs/controller.md, "Scan resampling"); 0: one reading per beam (the paper's)."""
    range_noise_m: float = 0.0
    """Standard deviation of the Gaussian noise on every reading that returns (0: exact)."""
    dropout: float = 0.0
    """Chance that a reading returns nothing (+inf, as drivers report a missed echo)."""
    blocked_width_rad: float = 0.0
    """Width of a sector of the lidar blocked (by the car's own mast or load): its readings
    return nothing (+inf, as the controller reads a sector no reading covers); 0: none."""
    blocked_centre_rad: float = math.pi
    """Direction of the blocked sector's centre from the car's heading, counter-clockwise
    (pi: behind)."""
    pose_noise_m: float = 0.0
    """Standard deviation of the Gaussian noise on each coordinate of the motion-capture
    position the car reads (0: exact)."""
    pose_noise_rad: float = 0.0
    """Standard deviation of the Gaussian noise on the motion-capture heading."""
    pose_latency_s: float = 0.0
    """Age of the motion-capture pose the car reads with each scan: where the car was this long
    before (at most one control period; 0: the pose at the scan's instant)."""

    def __post_init__(self) -> None:
        check_range(self, "lidar_readings", self.lidar_readings, 0, 100_000)
        check_range(self, "range_noise_m", self.range_noise_m, 0.0, 10.0)
        check_range(self, "dropout", self.dropout, 0.0, 1.0)
        check_range(self, "blocked_width_rad", self.blocked_width_rad, 0.0, 2 * math.pi)
        check_range(self, "blocked_centre_rad", self.blocked_centre_rad, -10.0, 10.0)
        check_range(self, "pose_noise_m", self.pose_noise_m, 0.0, 10.0)
        check_range(self, "pose_noise_rad", self.pose_noise_rad, 0.0, math.pi)
        check_range(self, "pose_latency_s", self.pose_latency_s, 0.0, 60.0)

    @property
    def scan_effects(self) -> bool:
        """Whether the scans differ from the exact lidar's."""
        return bool(
            self.lidar_readings or self.range_noise_m or self.dropout or self.blocked_width_rad
        )

    @property
    def pose_effects(self) -> bool:
        """Whether the pose the car reads differs from its true pose."""
        return bool(self.pose_noise_m or self.pose_noise_rad or self.pose_latency_s)


@dataclass(frozen=True)
class RoomConfig:
    """A room that is not the paper's square: walls along a closed polygon (`sim.room`)."""

    SECTION = "room"

    corners: tuple[tuple[float, float], ...] = ()
    """The walls' corners in order, in metres, the last joined to the first (all inside
    [0, arena.size_m]^2); (): the paper's square arena with its openings (`arena`)."""

    def __post_init__(self) -> None:
        if self.corners and len(self.corners) < 3:
            raise ConfigError(f"room.corners = {self.corners!r}: a room needs 3 corners or more")
        for corner in self.corners:
            if len(corner) != 2:
                raise ConfigError(f"room.corners: {corner!r} is not a point (x, y)")


@dataclass(frozen=True)
class ClutterConfig:
    """Static boxes on the floor that are not on the controller's map (`sim.room`)."""

    SECTION = "clutter"

    boxes: int = 0
    """Boxes per episode, each placed and turned at random inside the room (0: none)."""
    size_min_m: float = 0.3
    """Shortest side of a box."""
    size_max_m: float = 0.8
    """Longest side of a box."""

    def __post_init__(self) -> None:
        check_range(self, "boxes", self.boxes, 0, 100)
        check_range(self, "size_min_m", self.size_min_m, 0.0, 10.0, exclusive_low=True)
        check_range(
            self,
            "size_max_m",
            self.size_max_m,
            self.size_min_m,
            10.0,
            why="must be at least size_min_m",
        )


@dataclass(frozen=True)
class SpawnConfig:
    """Where the robot, the target and the obstacles are placed at the start of an episode."""

    SECTION = "spawn"

    wall_margin_m: float = 1.0
    """Least distance from the robot's and target's spawn points to any wall (paper: not given)."""
    target_min_distance_m: float = 0.5
    """Least initial distance from robot to target (paper: not given)."""
    target_max_distance_m: float = 3.0
    """Greatest initial distance from robot to target (paper: not given; 20 m = no limit)."""
    obstacle_clearance_m: float = 2.0
    """Least initial gap between an obstacle's surface and the robot's centre (not given; 2 s
    of the mean obstacle speed, so no layout is lost before the robot can act)."""

    def __post_init__(self) -> None:
        check_range(self, "wall_margin_m", self.wall_margin_m, 0.0, 500.0)
        check_range(self, "target_min_distance_m", self.target_min_distance_m, 0.0, 1e4)
        check_range(
            self,
            "target_max_distance_m",
            self.target_max_distance_m,
            self.target_min_distance_m,
            1e4,
            why="must be at least target_min_distance_m",
        )
        check_range(self, "obstacle_clearance_m", self.obstacle_clearance_m, 0.0, 500.0)


@dataclass(frozen=True)
class RewardConfig:
    """The paper's reward: +1 at the target, -1 on collision, else a shaping term (see `reward`)."""

    SECTION = "reward"

    success_reward: float = 1.0
    """Reward for coming within the robot radius l of the target (ends the episode)."""
    collision_reward: float = -1.0
    """Reward when the nearest surface is closer than l (ends the episode)."""
    c1: float = 0.01
    """Weight of the penalty for coming closer than 2l to a surface (paper: 0.01)."""
    c2: float = 0.002
    """Weight of the penalty on distance to target (paper: 0.002)."""
    c3_m: float = 10.0
    """Distance beyond which the target penalty stops growing (paper: c3 = 10)."""


LayoutSource = str
"""Where a world's static layouts come from: "" (none: the paper's square room), "barn" (the
300 published BARN worlds, committed: `sim.barn.BARN_FILE`), a generated family ("cave",
"rooms", or both as "cave+rooms": `sim.clutter`), or the path of a folder in BARN's format or of
a conversion file (.npz, `qnav barn-convert`)."""


@dataclass(frozen=True)
class LayoutConfig:
    """Static layouts (BARN's kind of world): cylinders on the floor, a start and a goal each,
    in place of the paper's square room (`sim.layouts`)."""

    SECTION = "layout"

    source: LayoutSource = ""
    """"": the paper's room. "barn": the 300 BARN worlds. "cave", "rooms", "cave+rooms": the
    generator's families. Else the path of a BARN-format folder or a conversion file."""
    split: Literal["train", "validation", "test"] = "train"
    """Which of a generated family's disjoint seed ranges to draw (ignored for files)."""
    worlds: int = 1000
    """How many worlds a generated family holds; of a folder or file, how many of its first
    worlds to use (all where it holds fewer)."""
    order: Literal["cycle", "random"] = "random"
    """Which layout an episode gets: "cycle" (episode e of every seed: layout e mod L, the
    benchmark's order) or "random" (drawn from the episode's seed and index)."""

    def __post_init__(self) -> None:
        if self.split not in ("train", "validation", "test"):
            raise ConfigError(f"layout.split = {self.split!r}: choose train, validation or test")
        if self.order not in ("cycle", "random"):
            raise ConfigError(f"layout.order = {self.order!r}: choose cycle or random")
        check_range(self, "worlds", self.worlds, 1, 1_000_000)


@dataclass(frozen=True)
class WorldConfig:
    """One scenario: arena, robot, sensor, dynamics, obstacles, spawning, reward, episode length."""

    SECTION = ""

    name: str = "walls-inertia"
    """Scenario name, for logs and files."""
    arena: ArenaConfig = field(default_factory=ArenaConfig)
    """The room."""
    lidar: LidarSpec | None = field(default_factory=LidarSpec)
    """The planar lidar, or None for the toy car that has only motion-capture poses."""
    lidar_turn_s: float = 0.0
    """A rotating lidar's turn in seconds (0.1 for 10 Hz): beam j leaves j / B of it after the
    turn's start, which ends at the observation, cast from where the car and the obstacles were
    then (`sim.world.rotating_scans`; each beam a whole scan's cost: evaluation, not training).
    0: every beam at the observation's instant (the paper's)."""
    robot_radius_m: float = 0.5
    """The paper's l: reach radius for the target and the collision distance (lost in the paper)."""
    reach_radius_m: float = 0.0
    """The target counts as reached within this distance of the robot's centre (BARN: 1 m);
    0: `robot_radius_m`, as the paper."""
    control_period_s: float = 0.2
    """Time between consecutive observations and decisions (paper: 0.2 s)."""
    dynamics: Dynamics = field(default_factory=InertiaDynamics)
    """How actions move the robot."""
    obstacles: ObstacleConfig = field(default_factory=ObstacleConfig)
    """The moving obstacles."""
    spawn: SpawnConfig = field(default_factory=SpawnConfig)
    """Initial placement."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """The reward."""
    max_episode_steps: int = 200
    """Steps before an episode is truncated (paper: 200 in training, 500 in tests)."""
    layout: LayoutConfig = field(default_factory=LayoutConfig)
    """Static layouts in place of the room (BARN's kind of world); none in the paper's."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """What a real lidar and motion capture add (none in the paper's)."""
    room: RoomConfig = field(default_factory=RoomConfig)
    """A room of another shape than the arena's square (none in the paper's)."""
    clutter: ClutterConfig = field(default_factory=ClutterConfig)
    """Static boxes the controller's map does not hold (none in the paper's)."""

    @property
    def realistic(self) -> bool:
        """Whether the world's geometry needs the room's ray caster (`sim.room`): a polygon
        room, clutter, or obstacles other than cylinders of one radius."""
        return bool(self.room.corners or self.clutter.boxes or self.obstacles.shaped)

    @property
    def reach_m(self) -> float:
        """The distance within which the target counts as reached."""
        return self.reach_radius_m or self.robot_radius_m

    def __post_init__(self) -> None:
        check_range(self, "robot_radius_m", self.robot_radius_m, 0.0, 100.0, exclusive_low=True)
        check_range(self, "reach_radius_m", self.reach_radius_m, 0.0, 100.0)
        check_range(self, "control_period_s", self.control_period_s, 0.0, 60.0, exclusive_low=True)
        check_range(self, "max_episode_steps", self.max_episode_steps, 1, 10_000_000)
        check_range(
            self,
            "lidar_turn_s",
            self.lidar_turn_s,
            0.0,
            self.control_period_s,
            why="one scan leaves per control period",
        )
        if self.lidar_turn_s and self.lidar is None:
            raise ConfigError(f"lidar_turn_s is set but {self.name} has no lidar")
        if self.layout.source and self.lidar_turn_s:
            raise ConfigError(
                "lidar_turn_s is set with layout.source: a rotating lidar is cast in the "
                "paper's room only"
            )
        check_range(
            self.sensor,
            "pose_latency_s",
            self.sensor.pose_latency_s,
            0.0,
            self.control_period_s,
            why="at most one control period",
        )
        self._check_sensor()
        if self.layout.source and (self.realistic or self.obstacles.walks):
            raise ConfigError(
                "room, clutter and obstacles other than straight-moving cylinders of one radius "
                "are for the paper's kind of room, not with layout.source"
            )
        if self.room.corners:
            self._check_polygon()
        elif not self.layout.source:
            self._check_room()

    def _check_sensor(self) -> None:
        """The physical lidar's readings must divide into the policy's beams."""
        readings = self.sensor.lidar_readings
        if (self.sensor.scan_effects or self.sensor.pose_effects) and self.lidar is None:
            raise ConfigError(f"sensor settings are set but {self.name} has no lidar")
        if readings and self.lidar is not None and self.lidar.num_beams % readings:
            raise ConfigError(
                f"sensor.lidar_readings = {readings} is out of range: it must divide "
                f"lidar.num_beams = {self.lidar.num_beams}"
            )

    def _check_polygon(self) -> None:
        """A polygon room must lie in the arena's square, which bounds it."""
        size = self.arena.size_m
        for x, y in self.room.corners:
            if not (0.0 <= x <= size and 0.0 <= y <= size):
                raise ConfigError(
                    f"room.corners: ({x}, {y}) lies outside [0, arena.size_m = {size}]^2"
                )

    def _check_room(self) -> None:
        """The paper's room must hold the spawn square, the obstacles and the openings."""
        size = self.arena.size_m
        free = size - 2 * self.spawn.wall_margin_m
        check_range(
            self.spawn,
            "wall_margin_m",
            self.spawn.wall_margin_m,
            self.robot_radius_m,
            (size - 1e-3) / 2,
            why="the robot must spawn clear of the walls and inside the arena",
        )
        if self.spawn.target_min_distance_m > free * math.sqrt(2):
            raise ConfigError(
                f"spawn.target_min_distance_m = {self.spawn.target_min_distance_m} is out of "
                "range: "
                f"allowed [0, {free * math.sqrt(2):.3f}] (the spawn square's diagonal)"
            )
        if self.obstacles.count:
            check_range(
                self.spawn,
                "obstacle_clearance_m",
                self.spawn.obstacle_clearance_m,
                self.robot_radius_m,
                size,
                exclusive_low=True,
                why="an episode must not start in a collision",
            )
            radius = self.obstacles.radius_m
            check_range(
                self.obstacles,
                "radius_m",
                radius,
                0.0,
                size / 4,
                exclusive_low=True,
                why="obstacles must be able to move inside the arena",
            )
            # Obstacles move in a square of side size - 2r; let them cover at most a quarter of it.
            room = (size - 2 * radius) ** 2
            most = int(0.25 * room / (math.pi * radius**2))
            check_range(
                self.obstacles,
                "count",
                self.obstacles.count,
                0,
                most,
                why=f"more obstacles than fit: at most {most} of radius {radius} m "
                f"in a {size} m arena",
            )
            keep_out = math.pi * (radius + self.spawn.obstacle_clearance_m) ** 2
            if keep_out > 0.5 * room:
                raise ConfigError(
                    f"spawn.obstacle_clearance_m = {self.spawn.obstacle_clearance_m} is too large: "
                    "the keep-out disc around the robot leaves no room to place obstacles"
                )
        for opening in self.arena.openings:
            if opening.width_m >= 2 * self.robot_radius_m:
                raise ConfigError(
                    f"arena.openings width_m = {opening.width_m} is out of range: allowed "
                    f"(0, {2 * self.robot_radius_m}) (the robot must not fit through an opening)"
                )


SCENARIOS: dict[str, WorldConfig] = {
    "walls-inertia": WorldConfig(name="walls-inertia"),
    "obstacles-inertia": WorldConfig(name="obstacles-inertia", obstacles=ObstacleConfig(count=5)),
    "walls-increment": WorldConfig(name="walls-increment", dynamics=IncrementDynamics()),
    # 0.5 s per step: 0.4 m/s, slower than the inertia robot's 0.5 m/s as the paper says (at
    # its stated 0.2 s the increment robot would run at 1 m/s); docs/simulator.md.
    "obstacles-increment": WorldConfig(
        name="obstacles-increment",
        dynamics=IncrementDynamics(),
        obstacles=ObstacleConfig(count=5),
        control_period_s=0.5,
    ),
    # The paper's toy car: motion-capture pose only, no lidar, so no obstacles it could see.
    "toycar-inertia": WorldConfig(name="toycar-inertia", lidar=None),
    "toycar-increment": WorldConfig(
        name="toycar-increment", lidar=None, dynamics=IncrementDynamics()
    ),
}
"""The paper's four scenarios (Tables I-IV) and the lidar-less variants for the toy car."""

BARN_ROBOT_RADIUS_M = 0.3
"""The robot's disc in BARN's worlds: between the Jackal's half length (0.254 m) and the
circle round its 0.508 x 0.430 m footprint (0.333 m). BARN's generator keeps its paths' cells
0.45 m from every cylinder centre, so a 0.3 m disc passes each published path with 7.5 cm to
spare on either side (docs/barn.md)."""

LAYOUT_SCENARIOS: dict[str, WorldConfig] = {
    # BARN's 300 worlds, in order: the benchmark (a test set: never train or tune on it).
    "barn": WorldConfig(
        name="barn",
        robot_radius_m=BARN_ROBOT_RADIUS_M,
        reach_radius_m=1.0,
        max_episode_steps=500,
        layout=LayoutConfig(source="barn", order="cycle"),
    ),
    # Worlds of BARN's family from the generator (sim/clutter.py): caves and rooms.
    "clutter": WorldConfig(
        name="clutter",
        robot_radius_m=BARN_ROBOT_RADIUS_M,
        reach_radius_m=1.0,
        max_episode_steps=500,
        layout=LayoutConfig(source="cave+rooms", split="train"),
    ),
}
# The cave family alone (BARN's own generator): the BARN learner's training worlds.
LAYOUT_SCENARIOS["cave"] = replace(
    LAYOUT_SCENARIOS["clutter"],
    name="cave",
    layout=replace(LAYOUT_SCENARIOS["clutter"].layout, source="cave"),
)
"""Worlds of static cylinders (BARN's kind): the paper's robot, lidar and actions, a 0.3 m disc,
BARN's protocol (success within 1 m of the goal, 500 steps of 0.2 s = BARN's 100 s)."""

SCENARIOS.update(LAYOUT_SCENARIOS)

REALISTIC_ROOM = WorldConfig(
    name="realistic-room",
    # An L-shaped room (10 x 8 m less a 2.5 x 2.5 m corner), its walls as a user measures them.
    room=RoomConfig(
        corners=((0.0, 0.0), (10.0, 0.0), (10.0, 5.5), (7.5, 5.5), (7.5, 8.0), (0.0, 8.0))
    ),
    arena=ArenaConfig(openings=()),
    lidar_turn_s=0.1,
    sensor=SensorConfig(
        lidar_readings=360,
        range_noise_m=0.02,
        dropout=0.02,
        blocked_width_rad=math.pi / 4,
        pose_noise_m=0.005,
        pose_noise_rad=0.005,
        pose_latency_s=0.03,
    ),
    obstacles=ObstacleConfig(
        count=5,
        radius_m=0.15,
        radius_max_m=0.3,
        box_share=1 / 3,
        legs_share=1 / 3,
        heading_walk_rad=0.15,
        speed_walk_mps=0.1,
        stop_probability=0.03,
    ),
    clutter=ClutterConfig(boxes=4),
)
"""A room that is not the simulator's, every setting of a real one on (docs/simulator.md, "A
realistic room"): an L-shaped room with boxes on the floor that no map holds; a 10 Hz lidar of
360 readings with 2 cm range noise, 2 % dropouts and its rear 45 degrees blocked; motion capture
5 mm and 0.3 degrees off and 30 ms late; five obstacles of 0.15-0.3 m, cylinders, boxes and
people's legs, that turn, change speed, stop and start."""

SCENARIOS[REALISTIC_ROOM.name] = REALISTIC_ROOM


def scenario(name: str, **changes: object) -> WorldConfig:
    """The named scenario's settings, optionally with top-level fields replaced."""
    try:
        config = SCENARIOS[name]
    except KeyError:
        raise ConfigError(
            f"unknown scenario {name!r}: choose one of {', '.join(SCENARIOS)}"
        ) from None
    return replace(config, **changes) if changes else config  # type: ignore[arg-type]


def load_world(
    name: str, settings_file: Path | None = None, assignments: list[str] | None = None
) -> WorldConfig:
    """A scenario's settings, changed by a TOML file and then by `section.field=value` strings."""
    return changed_world(scenario(name), settings_file, assignments)


def changed_world(
    config: WorldConfig, settings_file: Path | None = None, assignments: list[str] | None = None
) -> WorldConfig:
    """A world's settings changed by a TOML file and then by `section.field=value` strings."""
    if settings_file is not None:
        config = with_overrides(config, load_toml(settings_file))
    if assignments:
        config = with_overrides(config, parse_assignments(assignments))
    return config
