"""MAVLink 2 signing: key files, signed links, refused unsigned traffic, no key in any log."""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.mavlink import load_signing_key
from qnav.contracts.settings import from_dict, with_overrides
from qnav.firmware_bridge.daemon import Bridge
from qnav.firmware_bridge.link import serial0_warning
from qnav.firmware_bridge.settings import BridgeSettings
from tests.firmware_bridge.rig import Rig, wait_until

KEY = bytes(range(100, 132))
MakeRig = Callable[..., Rig]


@pytest.fixture
def key_file(tmp_path: Path) -> Path:
    path = tmp_path / "signing.key"
    path.write_text(KEY.hex() + "\n")
    path.chmod(0o600)
    return path


def test_key_file_reads_hex_raw_bytes_or_a_passphrase(tmp_path: Path) -> None:
    (tmp_path / "hex").write_text(KEY.hex().upper())
    (tmp_path / "raw").write_bytes(KEY)
    (tmp_path / "phrase").write_text("correct horse battery staple\n")
    assert load_signing_key(tmp_path / "hex") == KEY
    assert load_signing_key(tmp_path / "raw") == KEY
    # MAVProxy's `signing setup PASSPHRASE` uses the passphrase's SHA-256.
    expected = hashlib.sha256(b"correct horse battery staple").digest()
    assert load_signing_key(tmp_path / "phrase") == expected


def test_unreadable_or_empty_key_file_is_refused_by_name(tmp_path: Path) -> None:
    (tmp_path / "empty").write_text("\n")
    with pytest.raises(ConfigError, match="empty"):
        load_signing_key(tmp_path / "empty")
    with pytest.raises(ConfigError, match="missing"):
        load_signing_key(tmp_path / "missing")


def _signing(key_file: Path) -> dict[str, object]:
    return {"signing": {"enabled": True, "key_file": str(key_file)}}


def test_signed_bridge_drives_a_signed_vehicle_with_signed_messages_only(
    make_rig: MakeRig, key_file: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    rig = make_rig(bridge=_signing(key_file), vehicle={"signing_key_file": str(key_file)})
    rig.ready()
    rig.drive(0.5, 0.0, 0.4)
    assert rig.vehicle.pose()[0] > 0.02
    received = rig.vehicle.received()
    assert received and all(r.signed for r in received)
    assert rig.vehicle.counters["rejected"] == 0
    assert rig.bridge is not None
    text = caplog.text + repr(rig.bridge.settings) + repr(rig.bridge.link)
    assert KEY.hex() not in text.lower()
    assert str(list(KEY)) not in text and repr(KEY) not in text


def test_signing_vehicle_ignores_an_unsigned_bridge(make_rig: MakeRig, key_file: Path) -> None:
    no_disarm = {"failsafe": {"disarm_on_exit": False}}  # nobody would answer it
    rig = make_rig(bridge=no_disarm, vehicle={"signing_key_file": str(key_file)})
    wait_until(lambda: rig.vehicle.counters["rejected"] >= 3, what="unsigned packets refused")
    rig.drive(0.5, 0.0, 0.3)
    assert not rig.vehicle.armed
    assert rig.vehicle.received() == []
    assert rig.vehicle.pose() == (0.0, 0.0, 0.0)


def test_signing_bridge_refuses_an_unsigned_vehicle(make_rig: MakeRig, key_file: Path) -> None:
    rig = make_rig(bridge={**_signing(key_file), "failsafe": {"disarm_on_exit": False}})
    bridge = rig.bridge
    assert bridge is not None
    wait_until(lambda: bridge.counters["rejected"] >= 3, what="unsigned packets refused")
    time.sleep(0.2)
    assert rig.state().get("link_up") is False
    assert not rig.vehicle.armed


@pytest.mark.parametrize(
    ("connection", "serial0"),
    [
        ("tcp:127.0.0.1:5760", True),  # SITL's SERIAL0
        ("tcp:127.0.0.1:5770", True),  # SITL -I 1
        ("/dev/ttyACM0", True),  # a flight controller's USB
        ("/dev/serial/by-id/usb-ArduPilot_Pixhawk1_3E0031-if00", True),
        ("tcp:127.0.0.1:5762", False),  # SITL's SERIAL1
        ("/dev/ttyAMA0", False),  # a UART wired to TELEM2
        ("/dev/ttyUSB0", False),  # a USB-serial adapter on a TELEM port
        ("/dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A50285BI-if00-port0", False),
        ("udpin:0.0.0.0:14550", False),
    ],
)
def test_serial0_is_recognised(connection: str, serial0: bool) -> None:
    assert (serial0_warning(connection) is not None) is serial0


def test_a_signing_bridge_on_serial0_warns_loudly(
    key_file: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # ArduPilot accepts unsigned packets on SERIAL0 whatever the key: signing there is a false
    # sense of safety, and the log must say so.
    settings = from_dict(
        BridgeSettings,
        {
            "mavlink": {"connection": "tcp:127.0.0.1:5760"},
            "signing": {"enabled": True, "key_file": str(key_file)},
        },
    )
    with caplog.at_level(logging.WARNING, logger="qnav.firmware_bridge"):
        Bridge(settings)
    assert any("SIGNING PROTECTS NOTHING" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="qnav.firmware_bridge"):
        Bridge(with_overrides(settings, {"mavlink": {"connection": "tcp:127.0.0.1:5762"}}))
    assert not any("SIGNING" in r.getMessage() for r in caplog.records)
