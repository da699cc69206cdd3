"""A bridge, a MAVLink test vehicle and a zenoh peer on loopback, wired as on the car.

The test's zenoh session listens on a free TCP port with scouting off and the bridge connects
to it; the vehicle serves a free UDP port and the bridge sends to it. Timings are shortened so
the tests run in a fraction of a second each.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any, TypeVar

from qnav.contracts.daemon import free_port
from qnav.contracts.settings import with_overrides
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.contracts.wire import (
    COMMAND,
    POSE,
    VEHICLE_REQUEST,
    VEHICLE_STATE,
    Pose2D,
    Twist2D,
    decode_json_msg,
    encode_json_msg,
    encode_pose_msg,
    encode_twist_msg,
    key,
)
from qnav.firmware_bridge.daemon import Bridge
from qnav.firmware_bridge.settings import BridgeSettings
from qnav.simcar.mavlink_vehicle import MavlinkVehicle, MavlinkVehicleSettings

T = TypeVar("T")

FAST_BRIDGE: dict[str, Any] = {
    "mavlink": {
        "heartbeat_period_s": 0.1,
        "link_timeout_s": 0.3,
        "reconnect_period_s": 0.15,
    },
    "failsafe": {"command_timeout_s": 0.2, "stop_period_s": 0.05},
    "vehicle": {"state_period_s": 0.05, "arm_on_connect": True},
    # Calibrated as the test vehicle's full travel is read (MavlinkVehicleSettings.dynamics).
    "output": {"speed_at_full_throttle_mps": 1.0},
}
FAST_VEHICLE: dict[str, Any] = {
    "heartbeat_period_s": 0.05,
    "telemetry_period_s": 0.05,
    "rc_override_timeout_s": 1.0,
    "dynamics": {"linear_time_constant_s": 0.1, "angular_time_constant_s": 0.1},
}


def wait_until(condition: Callable[[], T], timeout_s: float = 5.0, what: str = "") -> T:
    """Poll `condition` until it returns something truthy (returned), or fail at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what or condition}")
        time.sleep(0.01)


class StateLog:
    """The vehicle states (JSON) a test's zenoh session hears, in order; `on_sample` is the
    subscriber's callback."""

    def __init__(self) -> None:
        self.states: list[dict[str, Any]] = []
        self._lock = threading.Lock()

    def on_sample(self, sample: Any) -> None:
        state = decode_json_msg(sample.payload.to_bytes())
        with self._lock:
            self.states.append(state)

    def newest(self) -> dict[str, Any]:
        """The newest state ({} before the first)."""
        with self._lock:
            return self.states[-1] if self.states else {}


def keep_commanding(
    command: Callable[[float, float], None],
    linear_mps: float,
    angular_radps: float,
    seconds: float,
    period_s: float,
) -> float:
    """`command(linear_mps, angular_radps)` every `period_s` for `seconds`, as a controller
    publishes; the time (time.monotonic) of the last one."""
    end = time.monotonic() + seconds
    while True:
        command(linear_mps, angular_radps)
        sent = time.monotonic()
        if sent >= end:
            return sent
        time.sleep(period_s)


def merged(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    """Nested dict merge (update wins)."""
    out = dict(base)
    for name, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(name), dict):
            out[name] = merged(out[name], value)
        else:
            out[name] = value
    return out


@dataclass
class Rig:
    """The three parts, and what the test's zenoh session saw."""

    session: Any
    vehicle: MavlinkVehicle
    bridge: Bridge | None
    zenoh_port: int
    mavlink_port: int
    heard: StateLog = field(default_factory=StateLog)
    _publishers: dict[str, Any] = field(default_factory=dict)

    def publish(self, topic_key: str, payload: bytes) -> None:
        """Put a payload on a key (publishers are declared once per key)."""
        if topic_key not in self._publishers:
            self._publishers[topic_key] = self.session.declare_publisher(topic_key)
        self._publishers[topic_key].put(payload)

    def command(self, linear_mps: float, angular_radps: float) -> None:
        """Publish one Twist command."""
        self.publish(key(COMMAND), encode_twist_msg(Twist2D(linear_mps, angular_radps)))

    def drive(self, linear_mps: float, angular_radps: float, seconds: float) -> float:
        """Publish a command every 50 ms for `seconds`; the time of the last one."""
        return keep_commanding(self.command, linear_mps, angular_radps, seconds, period_s=0.05)

    def request(self, value: dict[str, Any]) -> None:
        """Publish a vehicle request (JSON in a std_msgs/String)."""
        self.publish(key(VEHICLE_REQUEST), encode_json_msg(value))

    def publish_pose(self) -> None:
        """Publish the vehicle's true pose as the motion-capture pose."""
        x, y, yaw = self.vehicle.pose()
        self.publish(key(POSE), encode_pose_msg(Pose2D(time.time(), "map", x, y, yaw)))

    def state(self) -> dict[str, Any]:
        """The newest vehicle state seen on zenoh ({} before the first)."""
        return self.heard.newest()

    def counters(self) -> dict[str, int]:
        """The in-process bridge's counters."""
        assert self.bridge is not None
        return dict(self.bridge.counters)

    def send_garbage(self) -> None:
        """Three datagrams of junk to the bridge's MAVLink port, from another sender: a
        MAVLink 2 header with a bad CRC, text, and 0xFE bytes (MAVLink 1 starts announcing
        254-byte payloads)."""
        assert self.bridge is not None
        bridge_address = self.bridge.link.connection.port.getsockname()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rogue:
            for junk in (b"\xfd\x09\x00\x00\x00\x01\x01" + b"\x00" * 14, b"hello", b"\xfe" * 40):
                rogue.sendto(junk, bridge_address)

    def ready(self) -> None:
        """Wait until the bridge reports the link up and the vehicle armed."""
        wait_until(lambda: self.state().get("link_up") and self.state().get("armed"), what="armed")


def bridge_settings(zenoh_port: int, mavlink_port: int, **sections: Any) -> BridgeSettings:
    """Fast-timed bridge settings for the rig's ports, with sections overridden."""
    base = BridgeSettings(
        zenoh=ZenohSettings(connect=(f"tcp/127.0.0.1:{zenoh_port}",)),
    )
    overrides = merged(
        merged(FAST_BRIDGE, {"mavlink": {"connection": f"udpout:127.0.0.1:{mavlink_port}"}}),
        sections,
    )
    return with_overrides(base, overrides)


def vehicle_settings(mavlink_port: int, **fields: Any) -> MavlinkVehicleSettings:
    """Fast-timed vehicle settings serving the rig's port."""
    values = merged(FAST_VEHICLE, {"connection": f"udpin:127.0.0.1:{mavlink_port}", **fields})
    return with_overrides(MavlinkVehicleSettings(), values)


def start_rig(
    stack: ExitStack,
    *,
    bridge: dict[str, Any] | None = None,
    vehicle: dict[str, Any] | None = None,
    start_bridge: bool = True,
) -> Rig:
    """Start a zenoh peer, a vehicle and (unless told not to) a bridge; `stack` closes them."""
    zenoh_port, mavlink_port = free_port(socket.SOCK_STREAM), free_port(socket.SOCK_DGRAM)
    session = stack.enter_context(
        open_session(ZenohSettings(listen=(f"tcp/127.0.0.1:{zenoh_port}",), connect=()))
    )
    car = stack.enter_context(MavlinkVehicle(vehicle_settings(mavlink_port, **(vehicle or {}))))
    rig = Rig(session, car, None, zenoh_port, mavlink_port)
    subscriber = session.declare_subscriber(key(VEHICLE_STATE), rig.heard.on_sample)
    stack.callback(subscriber.undeclare)
    if start_bridge:
        rig.bridge = stack.enter_context(
            Bridge(bridge_settings(zenoh_port, mavlink_port, **(bridge or {})))
        )
    return rig


def rigs() -> Iterator[Callable[..., Rig]]:
    """Fixture body: a factory of rigs, all closed when the test ends."""
    with ExitStack() as stack:
        yield lambda **kwargs: start_rig(stack, **kwargs)
