"""A real autopilot as the simulated robot: its own pose estimate moves the robot.

`FirmwareVehicle` stands where `simcar.mavlink_vehicle.MavlinkVehicle` stands in
`simcar.car.SimCar`, for a run of the full stack on firmware (ArduPilot Rover SITL, `qnav stack
--vehicle sitl`): the bridge drives the autopilot, and the robot's pose in the simulated world is
the autopilot's LOCAL_POSITION_NED and ATTITUDE, as motion capture would give it. Lidar and walls
are simulated around that pose by the sim-car.

The autopilot cannot be put somewhere, so each episode's start is a frame change instead:
`set_pose(x, y, yaw)` makes the vehicle's pose at that moment read as (x, y, yaw), and later
poses move with it (a rigid transform). The vehicle should be at rest then (`wait_for_rest`).

It reads on a port of its own (SITL's SERIAL0 in `qnav stack`) with system id 250, never the
ground-station id, so the autopilot never takes it for the bridge's ground station.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

from qnav.contracts.daemon import Service
from qnav.contracts.mavlink import (
    MAV_MODE_FLAG_SAFETY_ARMED,
    drain,
    mode_name,
    ned_to_enu,
    open_connection,
    wrap_pi,
)
from qnav.contracts.transport import StoppedError

log = logging.getLogger("qnav.simcar.firmware_vehicle")

MAV_CMD_SET_MESSAGE_INTERVAL = 511
MESSAGE_IDS = {"LOCAL_POSITION_NED": 32, "ATTITUDE": 30}


@dataclass(frozen=True)
class FirmwareVehicleSettings:
    """Where to read the autopilot's pose, and how often."""

    connection: str = "tcp:127.0.0.1:5760"
    """pymavlink connection to the autopilot (SITL's SERIAL0: tcp:127.0.0.1:5760)."""
    system_id: int = 250
    """Our system id on that link (never the bridge's ground-station id, 255)."""
    vehicle_system_id: int = 1
    """The autopilot's system id."""
    message_rate_hz: float = 20.0
    """LOCAL_POSITION_NED and ATTITUDE are asked for at this rate (Rover: at most half its
    SCHED_LOOP_RATE, 50 Hz by default)."""
    ready_mode: str = "GUIDED"
    """`armed` is true only when armed in this mode (empty: any mode)."""


def frame_change(
    anchor_vehicle: tuple[float, float, float], anchor_world: tuple[float, float, float]
) -> tuple[float, float, float, float]:
    """(cos, sin, tx, ty) of the rigid transform taking `anchor_vehicle` onto `anchor_world`."""
    turn = anchor_world[2] - anchor_vehicle[2]
    c, s = math.cos(turn), math.sin(turn)
    tx = anchor_world[0] - (c * anchor_vehicle[0] - s * anchor_vehicle[1])
    ty = anchor_world[1] - (s * anchor_vehicle[0] + c * anchor_vehicle[1])
    return c, s, tx, ty


def apply_frame(
    transform: tuple[float, float, float, float], pose: tuple[float, float, float]
) -> tuple[float, float, float]:
    """A vehicle pose (x, y, yaw) in the episode's world frame."""
    c, s, tx, ty = transform
    x, y, yaw = pose
    return c * x - s * y + tx, s * x + c * y + ty, wrap_pi(yaw + math.atan2(s, c))


class FirmwareVehicle(Service):
    """The autopilot's pose, armed flag and mode, read on a MAVLink link of its own."""

    def __init__(self, settings: FirmwareVehicleSettings) -> None:
        self.settings = settings
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._north_east: tuple[float, float] | None = None
        self._velocity_ne: tuple[float, float] = (math.nan, math.nan)
        self._yaw_ned: float | None = None
        self._armed = False
        self._mode = ""
        self._transform = (1.0, 0.0, 0.0, 0.0)
        self.samples = 0
        """LOCAL_POSITION_NED messages received."""
        self._conn: Any = None
        self._thread: threading.Thread | None = None

    def start(self, timeout_s: float = 30.0, stop: threading.Event | None = None) -> None:
        """Connect (retrying while the autopilot's port is not open yet) and start reading;
        StoppedError once `stop` is set while retrying."""
        deadline = time.monotonic() + timeout_s
        stop = stop or threading.Event()
        while True:
            try:
                self._conn = open_connection(
                    self.settings.connection,
                    baud_rate=115200,
                    system_id=self.settings.system_id,
                    component_id=1,
                )
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                if stop.wait(0.2):
                    raise StoppedError("stopped before the autopilot's port opened") from None
        self._thread = threading.Thread(target=self._loop, name="firmware-vehicle", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        if self._conn is not None:
            self._conn.close()

    def _request_streams(self) -> None:
        interval_us = 1e6 / self.settings.message_rate_hz
        for message_id in MESSAGE_IDS.values():
            self._conn.mav.command_long_send(
                self.settings.vehicle_system_id, 1, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                message_id, interval_us, 0, 0, 0, 0, 0,
            )  # fmt: skip

    def _loop(self) -> None:
        next_request_s = 0.0
        while not self._stopping.is_set():
            now = time.monotonic()
            if now >= next_request_s:  # again now and then: a booting autopilot may miss it
                self._request_streams()
                next_request_s = now + 2.0
            try:
                messages = drain(self._conn, 0.02)
            except (OSError, ConnectionError) as error:
                log.warning("autopilot link: %s", error)
                time.sleep(0.1)
                continue
            for message in messages:
                if message.get_srcSystem() != self.settings.vehicle_system_id:
                    continue
                if message.get_srcComponent() != 1:
                    continue
                self._take(message)

    def _take(self, message: Any) -> None:
        kind = message.get_type()
        with self._lock:
            if kind == "LOCAL_POSITION_NED":
                self._north_east = (float(message.x), float(message.y))
                self._velocity_ne = (float(message.vx), float(message.vy))
                self.samples += 1
            elif kind == "ATTITUDE":
                self._yaw_ned = float(message.yaw)
            elif kind == "HEARTBEAT":
                self._armed = bool(message.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
                self._mode = mode_name(message.custom_mode)

    def vehicle_pose(self) -> tuple[float, float, float] | None:
        """The autopilot's own pose in our frame (x east, y north, yaw counter-clockwise from
        x), or None before it reported one."""
        with self._lock:
            if self._north_east is None or self._yaw_ned is None:
                return None
            return ned_to_enu(self._north_east[0], self._north_east[1], self._yaw_ned)

    def pose(self) -> tuple[float, float, float]:
        """The pose in the episode's world frame (see `set_pose`)."""
        pose = self.vehicle_pose()
        if pose is None:
            raise RuntimeError(f"no pose from the autopilot on {self.settings.connection} yet")
        with self._lock:
            transform = self._transform
        return apply_frame(transform, pose)

    def set_pose(self, x_m: float, y_m: float, yaw_rad: float) -> None:
        """From now on the vehicle's present pose reads as (x, y, yaw)."""
        pose = self.vehicle_pose()
        if pose is None:
            raise RuntimeError(f"no pose from the autopilot on {self.settings.connection} yet")
        transform = frame_change(pose, (x_m, y_m, yaw_rad))
        with self._lock:
            self._transform = transform

    def speed_mps(self) -> float:
        """Ground speed from LOCAL_POSITION_NED (nan before one came)."""
        with self._lock:
            return math.hypot(*self._velocity_ne)

    def wait_for_rest(self, rest_speed_mps: float, timeout_s: float) -> bool:
        """Wait until the ground speed is below `rest_speed_mps`; False at the timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.speed_mps() < rest_speed_mps:
                return True
            time.sleep(0.02)
        return False

    @property
    def armed(self) -> bool:
        """Armed, in `ready_mode` (if set), with a pose: ready for an episode."""
        with self._lock:
            ready = self._armed and self._north_east is not None and self._yaw_ned is not None
            return ready and (
                not self.settings.ready_mode or self._mode == self.settings.ready_mode
            )

    @property
    def mode(self) -> str:
        with self._lock:
            return self._mode
