"""Settings of the controller daemon (`qnav controller --config FILE`).

A settings file has one table per section below; every key is optional except
`controller.policy`. `qnav controller --print-config` prints them all with their meanings, and
`config/controller.toml` is that output, commented.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from qnav.contracts import wire
from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import (
    check_range,
    from_dict,
    load_toml,
    parse_assignments,
    with_overrides,
)
from qnav.contracts.transport import ZenohSettings
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.perception import TrackerSettings
from qnav.controller.proximity import ProximitySettings
from qnav.controller.scan import BelowRangeMin

Trigger = Literal["period", "scan"]
TargetKind = Literal["pose", "point"]


@dataclass(frozen=True)
class ControllerSettings:
    """The policy to run and how the daemon paces its decisions."""

    SECTION = "controller"

    policy: str = ""
    """The exported policy file (ONNX); a relative path is taken from the settings file's folder."""
    backend: Literal["onnxruntime", "numpy"] = "onnxruntime"
    """Runtime backend: onnxruntime, or numpy on boards without an onnxruntime wheel."""
    trigger: Trigger = "period"
    """When to decide: "period" (every control period of the policy, on absolute monotonic
    deadlines, with the newest inputs) or "scan" (as soon as a scan arrives; the safety rules are
    still checked every period). Use "scan" only with a lidar that runs at the policy's rate."""
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    """Logging threshold."""
    log_interval_s: float = 5.0
    """Malformed-input warnings of one input are logged at most once per this interval (the
    rest are counted and summarised in the next warning)."""

    def __post_init__(self) -> None:
        check_range(self, "log_interval_s", self.log_interval_s, 0.0, 3600.0)


@dataclass(frozen=True)
class LidarSettings:
    """How a scan of any lidar becomes the policy's beams (docs/controller.md: resampling)."""

    SECTION = "lidar"

    mount_yaw_rad: float = 0.0
    """Yaw of the lidar's x axis from the car's heading, counter-clockwise (pi: facing back)."""
    frame_id: str = ""
    """Required header frame_id of scans ("": any); a scan in another frame is malformed."""
    below_range_min: BelowRangeMin = "invalid"
    """Finite readings below the scan's range_min (0 included): "invalid" (ignored, like NaN),
    "no_return" (drivers that write 0 for no echo) or "obstacle" (read as 0 m)."""
    uncovered_range_m: float = math.inf
    """Range of a policy beam that no valid reading covers (outside a partial field of view, or
    only invalid readings): inf reads as no return, 0 as blocked."""
    max_invalid_fraction: float = 0.5
    """A scan with a larger fraction of invalid readings is malformed (not used), so a failing
    lidar stops the car through the scan timeout."""
    min_readings: int = 50
    """A scan with fewer readings is malformed: no lidar the policy can use has so few (a
    single reading would be stretched over every beam)."""
    min_field_of_view_rad: float = math.pi
    """A scan covering less than this angle (readings times abs(angle_increment)) is malformed."""

    def __post_init__(self) -> None:
        check_range(self, "mount_yaw_rad", self.mount_yaw_rad, -2 * math.pi, 2 * math.pi)
        check_range(self, "min_readings", self.min_readings, 1, 100_000)
        if math.isnan(self.uncovered_range_m) or self.uncovered_range_m < 0:
            raise ConfigError(
                f"lidar.uncovered_range_m = {self.uncovered_range_m!r} is out of range: "
                "allowed [0, inf]"
            )
        check_range(self, "max_invalid_fraction", self.max_invalid_fraction, 0.0, 1.0)
        check_range(self, "min_field_of_view_rad", self.min_field_of_view_rad, 0.0, 2 * math.pi)


@dataclass(frozen=True)
class SafetySettings:
    """When the controller stops the car instead of asking the policy."""

    SECTION = "safety"

    scan_timeout_s: float = 0.0
    """A scan older than this (since it arrived) stops the car; 0: two control periods."""
    pose_timeout_s: float = 0.0
    """A pose older than this (since it arrived) stops the car; 0: two control periods."""
    target_kind: TargetKind = "pose"
    """Target message: "pose" (geometry_msgs/PoseStamped) or "point" (PointStamped)."""
    target_tolerance_m: float = 0.5
    """The target is reached within this distance (the simulator's reach radius is 0.5 m); the car
    then stops until a different target arrives."""
    frame_id: str = ""
    """Required header frame_id of poses and targets ("": any, but the two must agree when both
    name one); a pose or target in another frame is malformed."""
    estop_start_latched: bool = False
    """Start with the emergency stop latched, so that the car moves only after a release."""
    max_position_m: float = 1000.0
    """A pose or target farther than this from the frame's origin is malformed: no room the car
    drives in is that large, and 1e308 is a broken message, not a place."""

    def __post_init__(self) -> None:
        check_range(self, "max_position_m", self.max_position_m, 0.0, 1e7, exclusive_low=True)
        check_range(self, "scan_timeout_s", self.scan_timeout_s, 0.0, 60.0)
        check_range(self, "pose_timeout_s", self.pose_timeout_s, 0.0, 60.0)
        check_range(
            self, "target_tolerance_m", self.target_tolerance_m, 0.0, 100.0, exclusive_low=True
        )


PolicySource = Literal["file", "server"]


@dataclass(frozen=True)
class PolicySourceSettings:
    """Where the policy comes from: the file alone, or also a `qnav serve` on the desktop
    (docs/serve.md)."""

    SECTION = "policy"

    source: PolicySource = "file"
    """"file": controller.policy only. "server": start with controller.policy, then take the
    policies a `qnav serve` announces, each verified (signature, sha256, contract, one trial
    run) and swapped in only while the car is stopped; any failure keeps the running one."""
    public_key: str = ""
    """The server's Ed25519 public key (PEM, from `qnav keys`); required with source = "server".
    A relative path is taken from the settings file's folder."""
    cache_dir: str = ""
    """Where fetched policy files are written ("": a temporary folder, removed at exit). A
    relative path is taken from the settings file's folder."""
    chunk_timeout_s: float = 2.0
    """A chunk of a policy file not received within this fails the transfer."""
    retry_interval_s: float = 10.0
    """A version whose transfer failed is fetched again at most this often."""
    max_file_bytes: int = 64 * 1024 * 1024
    """Announced policy files larger than this are refused unfetched."""

    def __post_init__(self) -> None:
        if self.source not in ("file", "server"):
            raise ConfigError(f"policy.source = {self.source!r} is not one of file, server")
        check_range(self, "chunk_timeout_s", self.chunk_timeout_s, 0.0, 600.0, exclusive_low=True)
        check_range(self, "retry_interval_s", self.retry_interval_s, 0.0, 86400.0)
        check_range(self, "max_file_bytes", self.max_file_bytes, 1, 1 << 30)

    def public_key_path(self) -> Path:
        """The public key file; ConfigError naming `policy.public_key` if unset or missing."""
        if not self.public_key:
            raise ConfigError(
                'policy.public_key is not set: policy.source = "server" needs the server\'s '
                "public key (qnav keys DIR writes DIR/policy-signing.pub)"
            )
        path = Path(self.public_key)
        if not path.is_file():
            raise ConfigError(f"policy.public_key = {str(path)!r}: no such file")
        return path


@dataclass(frozen=True)
class TopicSettings:
    """ROS topic names (without namespace); zenoh keys are `[zenoh.namespace/]NAME`, as
    zenoh-bridge-ros2dds maps them."""

    SECTION = "topics"

    scan: str = wire.SCAN.name
    """Lidar scans in (sensor_msgs/msg/LaserScan)."""
    pose: str = wire.POSE.name
    """Motion-capture poses in (geometry_msgs/msg/PoseStamped)."""
    target: str = ""
    """Targets in ("": goal_pose for safety.target_kind = "pose", goal_point for "point")."""
    estop: str = wire.ESTOP.name
    """Emergency stop in (std_msgs/msg/Bool: true presses it)."""
    estop_release: str = wire.ESTOP_RELEASE.name
    """Release requests in (std_msgs/msg/Bool: true asks to release a latched emergency stop)."""
    command: str = wire.COMMAND.name
    """Motor commands out (geometry_msgs/msg/Twist: linear.x, angular.z)."""
    status: str = wire.CONTROLLER_STATUS.name
    """Status out (std_msgs/msg/String holding one JSON object per decision)."""
    policy_announcement: str = wire.POLICY_ANNOUNCEMENT.name
    """Policy announcements in, from `qnav serve` (std_msgs/msg/String, JSON; read only with
    policy.source = "server")."""

    def __post_init__(self) -> None:
        names = ("scan", "pose", "estop", "estop_release", "command", "status")
        for name in (*names, "policy_announcement"):
            value = getattr(self, name)
            if not value.strip("/") or any(c in value for c in "*$?# "):
                raise ConfigError(f"topics.{name} = {value!r} is not a usable topic name")


@dataclass(frozen=True)
class DaemonConfig:
    """Everything `qnav controller` reads from its settings file."""

    SECTION = ""

    controller: ControllerSettings = field(default_factory=ControllerSettings)
    """The policy and the pacing."""
    lidar: LidarSettings = field(default_factory=LidarSettings)
    """Scan resampling."""
    safety: SafetySettings = field(default_factory=SafetySettings)
    """Stop rules."""
    proximity: ProximitySettings = field(default_factory=ProximitySettings)
    """The proximity stop: a safety field around the car that overrides every decision."""
    policy: PolicySourceSettings = field(default_factory=PolicySourceSettings)
    """Policies from a server."""
    topics: TopicSettings = field(default_factory=TopicSettings)
    """Topic names."""
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    """How to join the zenoh network."""
    lookahead: LookaheadSettings = field(default_factory=LookaheadSettings)
    """The look ahead that may overrule the policy where another action is less likely to
    collide (the shield by default: it needs `lookahead.room_size_m`)."""
    tracker: TrackerSettings = field(default_factory=TrackerSettings)
    """How the look ahead tracks obstacles in the scans."""

    def target_topic(self) -> wire.Topic:
        """The target topic, named by `topics.target` or by the target kind."""
        topic = wire.TARGET_POSE if self.safety.target_kind == "pose" else wire.TARGET_POINT
        return wire.Topic(self.topics.target or topic.name, topic.ros_type)

    def policy_path(self) -> Path:
        """The policy file; ConfigError naming `controller.policy` if unset or missing."""
        if not self.controller.policy:
            raise ConfigError("controller.policy is not set: name the exported policy file")
        path = Path(self.controller.policy)
        if not path.is_file():
            raise ConfigError(f"controller.policy = {str(path)!r}: no such file")
        return path


def load_config(path: Path | None, assignments: list[str] | None = None) -> DaemonConfig:
    """Settings from a TOML file (defaults without one) and `section.field=value` overrides.

    A relative `controller.policy`, `policy.public_key` or `policy.cache_dir` in the file is taken
    from the file's folder.
    """
    config = DaemonConfig()
    if path is not None:
        config = from_dict(DaemonConfig, load_toml(path))
        policy = config.controller.policy
        if policy and not Path(policy).is_absolute():
            config = replace(
                config,
                controller=replace(config.controller, policy=str(path.parent / policy)),
            )
        source = config.policy
        public_key, cache_dir = (
            str(path.parent / value) if value and not Path(value).is_absolute() else value
            for value in (source.public_key, source.cache_dir)
        )
        config = replace(config, policy=replace(source, public_key=public_key, cache_dir=cache_dir))
    if assignments:
        config = with_overrides(config, parse_assignments(assignments))
    return config
