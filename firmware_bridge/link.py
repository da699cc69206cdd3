"""The bridge's MAVLink link: one pymavlink connection, two source identities, a reopen.

Messages the bridge sends as the companion computer (heartbeat, guided targets, vision poses,
commands) carry the vehicle's system id and component 191; RC overrides and MANUAL_CONTROL
carry the ground-station system id, the only one Rover takes them from. Sends come from the
zenoh callback threads and the bridge's own thread, so they share a lock: pymavlink's sequence
number and signing timestamp are not thread-safe.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import Counter
from typing import Any

from qnav.contracts.mavlink import drain, mavutil, open_connection
from qnav.firmware_bridge.settings import MavlinkSettings

log = logging.getLogger(__name__)


class MavlinkLink:
    """The connection to the autopilot; `send` is safe from any thread, `poll` from one."""

    def __init__(self, settings: MavlinkSettings, signing_key: bytes | None) -> None:
        self.settings = settings
        self.signing = signing_key is not None
        self._key = signing_key
        self._lock = threading.Lock()
        self._conn: Any = None
        self._signing_timestamp = 0
        self.encoder: Any = mavutil().mavlink.MAVLink(None)
        """Builds message objects (`encoder.heartbeat_encode(...)`) for `send`."""
        self.sent: Counter[str] = Counter()
        """Messages sent, by type."""
        self.send_errors = 0
        self.receive_errors = 0

    def __repr__(self) -> str:  # the key stays out of any log line that prints the link
        return f"MavlinkLink({self.settings.connection!r}, signing={self.signing})"

    @property
    def connection(self) -> Any:
        """The pymavlink connection (None while closed), for diagnostics."""
        return self._conn

    @property
    def is_open(self) -> bool:
        """True while a connection is open."""
        return self._conn is not None

    def open(self) -> None:
        """Open (or reopen) the connection; the old one, if any, is closed.

        Raises ConfigError for a malformed connection string and OSError when the port cannot
        be opened (no such serial device, UDP port in use).
        """
        conn = open_connection(
            self.settings.connection,
            baud_rate=self.settings.baud_rate,
            system_id=self.settings.vehicle_system_id,
            component_id=self.settings.companion_component_id,
            signing_key=self._key,
            signing_timestamp=self._signing_timestamp,
        )
        with self._lock:
            old, self._conn = self._conn, conn
        if old is not None:
            _close_quietly(old)

    def close(self) -> None:
        """Close the connection (sends fail quietly afterwards)."""
        with self._lock:
            old, self._conn = self._conn, None
        if old is not None:
            _close_quietly(old)

    def send(self, message: Any, *, as_gcs: bool = False) -> bool:
        """Send one message as the companion, or as the ground station; False if it failed."""
        with self._lock:
            conn = self._conn
            if conn is None:
                return False
            mav = conn.mav
            mav.srcSystem = (
                self.settings.gcs_system_id if as_gcs else self.settings.vehicle_system_id
            )
            mav.srcComponent = self.settings.companion_component_id
            try:
                mav.send(message)
            except OSError as error:
                self.send_errors += 1
                log.debug("MAVLink send failed: %s", error)
                return False
            self._signing_timestamp = mav.signing.timestamp
            self.sent[message.get_type()] += 1
            return True

    def poll(self, timeout_s: float) -> list[Any]:
        """Messages received within `timeout_s` (call from one thread only)."""
        conn = self._conn
        if conn is None:
            time.sleep(timeout_s)
            return []
        try:
            return drain(conn, timeout_s)
        except ConnectionError as error:
            log.warning("MAVLink connection lost: %s", error)
            self.close()
            return []
        except Exception as error:  # pymavlink raises its own types too; the loop must go on
            self.receive_errors += 1
            log.debug("MAVLink receive failed: %s", error)
            time.sleep(timeout_s)
            return []


SITL_SERIAL0_PORTS = frozenset(5760 + 10 * instance for instance in range(10))
"""ArduPilot SITL serves SERIAL0 on TCP 5760 (+ 10 per instance, `-I`)."""


def serial0_warning(connection: str) -> str | None:
    """Why `connection` is probably the autopilot's SERIAL0, where ArduPilot takes unsigned
    packets whatever the signing setup (GCS_Signing.cpp: channel 0 is "the secure channel",
    USB on a flight controller), or None.

    A USB CDC device (/dev/ttyACM*, or a /dev/serial/by-id/usb-*-if00 name; a USB-serial
    adapter's ends in -port0) is the board's USB port, SERIAL0; TCP 5760 is SITL's SERIAL0. A
    UART (/dev/ttyAMA0, /dev/ttyS*, /dev/ttyUSB* adapters on a TELEM port) or UDP from a
    telemetry link is not."""
    lowered = connection.lower()
    if lowered.startswith("/dev/ttyacm") or (
        lowered.startswith("/dev/serial/by-id/usb-") and lowered.endswith("-if00")
    ):
        return f"{connection} is a USB port: the autopilot's SERIAL0"
    if lowered.startswith(("tcp:", "tcpin:")):
        try:
            port = int(connection.rsplit(":", 1)[1])
        except ValueError:
            return None
        if port in SITL_SERIAL0_PORTS:
            return f"{connection} is TCP port {port}: ArduPilot SITL's SERIAL0"
    return None


def _close_quietly(conn: Any) -> None:
    with contextlib.suppress(OSError):
        conn.close()
