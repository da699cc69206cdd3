"""The MAVLink link over a serial device (a pseudo-terminal stands in for the UART)."""

from __future__ import annotations

import os
import select
import time
from typing import Any

from qnav.contracts.mavlink import mavutil
from qnav.firmware_bridge.link import MavlinkLink
from qnav.firmware_bridge.settings import MavlinkSettings


def test_serial_device_with_baud_rate_carries_mavlink_both_ways() -> None:
    autopilot_fd, device_fd = os.openpty()
    device = os.ttyname(device_fd)
    link = MavlinkLink(MavlinkSettings(connection=device, baud_rate=57600), signing_key=None)
    autopilot = mavutil().mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        link.open()
        os.write(autopilot_fd, autopilot.heartbeat_encode(10, 3, 0, 0, 3).pack(autopilot))
        deadline = time.monotonic() + 3
        received: list[Any] = []
        while not received and time.monotonic() < deadline:
            received = [m for m in link.poll(0.05) if m.get_type() == "HEARTBEAT"]
        assert received and received[0].get_srcSystem() == 1
        assert link.send(link.encoder.heartbeat_encode(18, 8, 0, 0, 4))
        assert select.select([autopilot_fd], [], [], 3)[0]
        messages = autopilot.parse_buffer(os.read(autopilot_fd, 512)) or []
        assert [(m.get_type(), m.type, m.get_srcComponent()) for m in messages] == [
            ("HEARTBEAT", 18, 191)
        ]
    finally:
        link.close()
        os.close(autopilot_fd)
        os.close(device_fd)
