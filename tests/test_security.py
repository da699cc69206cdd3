"""Nobody gets in where they don't belong (issue 18 part 6): zenoh with mutual TLS and access
control, on loopback with real sessions and certificates made by `qnav certs`; and the network
a daemon exposes when given a zenoh configuration file."""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from qnav.certs import IDENTITIES, make_certificates
from qnav.cli import main
from qnav.contracts import wire
from qnav.contracts.daemon import free_port
from qnav.contracts.errors import ConfigError
from qnav.contracts.transport import (
    ZenohSettings,
    exposed_endpoints,
    network_view,
    open_session,
    secure_hub_config,
    zenoh_config,
)
from qnav.simcar.mavlink_vehicle import MavlinkVehicle
from tests.firmware_bridge.rig import vehicle_settings, wait_until

ROOT = Path(__file__).resolve().parents[1]
PUBLISHERS = {name: tuple(t.name for t in topics) for name, topics in wire.PUBLISHERS.items()}

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """Certificates for every identity and an intruder, with their zenoh configs."""
    folder = tmp_path_factory.mktemp("certs")
    endpoint = f"tls/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    done = subprocess.run(
        [sys.executable, "-m", "qnav", "certs", str(folder), "--endpoint", endpoint, "--names",
         "hub", "controller", "bridge", "sensors", "operator", "recorder", "server", "intruder"],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return folder, endpoint


def _session(folder: Path, name: str) -> Any:
    return open_session(ZenohSettings(config_file=str(folder / f"zenoh-{name}.json5")))


@pytest.fixture(scope="module")
def hub(certs: tuple[Path, str]) -> Iterator[Any]:
    folder, _ = certs
    with _session(folder, "hub") as session:
        yield session


class Heard:
    """Everything a listening identity receives, by key."""

    def __init__(self, session: Any) -> None:
        self.lock = threading.Lock()
        self.samples: list[tuple[str, bytes]] = []
        self.subscriber = session.declare_subscriber("**", self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        with self.lock:
            self.samples.append((str(sample.key_expr), bytes(sample.payload.to_bytes())))

    def payloads(self, key: str) -> list[bytes]:
        with self.lock:
            return [payload for k, payload in self.samples if k == key]


def test_only_the_controller_commands_and_only_the_operator_arms_or_releases(
    certs: tuple[Path, str], hub: Any
) -> None:
    folder, _ = certs
    with (
        _session(folder, "recorder") as listener,
        _session(folder, "controller") as controller,
        _session(folder, "operator") as operator,
        _session(folder, "bridge") as bridge,
        _session(folder, "intruder") as intruder,
    ):
        heard = Heard(listener)
        time.sleep(0.5)
        arm = wire.encode_json_msg({"arm": True})
        release = wire.encode_bool_msg(True)
        for _ in range(3):
            for who, session in (("intruder", intruder), ("bridge", bridge)):
                session.put(wire.key(wire.COMMAND), who.encode())
                session.put(wire.key(wire.VEHICLE_REQUEST), arm)
                session.put(wire.key(wire.ESTOP_RELEASE), release)
            intruder.put(wire.key(wire.VEHICLE_STATE), b"forged")
            controller.put(wire.key(wire.COMMAND), b"controller")
            operator.put(wire.key(wire.VEHICLE_REQUEST), arm)
            operator.put(wire.key(wire.ESTOP_RELEASE), release)
            bridge.put(wire.key(wire.VEHICLE_STATE), b"state")
            time.sleep(0.05)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(heard.payloads("qnav/vehicle_state")) < 3:
            time.sleep(0.05)
        time.sleep(0.3)
        assert heard.payloads("cmd_vel") == [b"controller"] * 3
        assert heard.payloads("qnav/vehicle_request") == [arm] * 3
        assert heard.payloads("qnav/estop_release") == [release] * 3
        assert heard.payloads("qnav/vehicle_state") == [b"state"] * 3


def test_a_peer_without_a_certificate_cannot_join(certs: tuple[Path, str], hub: Any) -> None:
    folder, endpoint = certs
    config = json.loads((folder / "zenoh-controller.json5").read_text())
    tls = config["transport"]["link"]["tls"]
    del tls["connect_certificate"], tls["connect_private_key"]
    config["connect"]["timeout_ms"] = 2000
    path = folder / "zenoh-nocert.json5"
    path.write_text(json.dumps(config))
    with pytest.raises(Exception, match="cannot open a zenoh session"):
        open_session(ZenohSettings(config_file=str(path)))
    # And plain TCP to the same port is no way in either.
    plain = endpoint.replace("tls/", "tcp/")
    settings = ZenohSettings(connect=(plain,), extra={"connect/timeout_ms": 2000})
    with pytest.raises(Exception, match="cannot open a zenoh session"):
        open_session(settings)


def test_the_controller_daemon_runs_with_its_secure_config(
    certs: tuple[Path, str], hub: Any, tmp_path: Path
) -> None:
    folder, _ = certs
    policy = ROOT / "tests" / "data" / "playback" / "policy.onnx"
    with _session(folder, "recorder") as listener:
        heard = Heard(listener)
        daemon = subprocess.Popen(
            [sys.executable, "-m", "qnav", "controller", "--policy", str(policy),
             "--set", f'zenoh.config_file="{folder / "zenoh-controller.json5"}"',
             "--set", 'lookahead.mode="off"'],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not heard.payloads("cmd_vel"):
                time.sleep(0.1)
            assert heard.payloads("cmd_vel"), "no command came through the secure hub"
            assert wire.decode_twist_msg(heard.payloads("cmd_vel")[0]) == wire.STOP
        finally:
            daemon.terminate()
            _, stderr = daemon.communicate(timeout=20)
        assert "multicast scouting off" in stderr


def test_the_shipped_secure_config_is_the_generated_one() -> None:
    text = (ROOT / "config" / "zenoh-secure.json5").read_text()
    body = "\n".join(line for line in text.splitlines() if not line.startswith("//"))
    expected = secure_hub_config("certs", "tls/127.0.0.1:7447", PUBLISHERS)
    assert json.loads(body) == expected


def test_a_minimal_user_config_neither_scouts_nor_listens_everywhere(tmp_path: Path) -> None:
    path = tmp_path / "minimal.json5"
    path.write_text('{ mode: "peer" }')
    listen, multicast = network_view(zenoh_config(ZenohSettings(config_file=str(path))))
    assert (listen, multicast) == ([], False)
    path.write_text('{ mode: "peer", listen: { endpoints: ["tcp/0.0.0.0:7448"] } }')
    listen, _ = network_view(zenoh_config(ZenohSettings(config_file=str(path))))
    assert exposed_endpoints(listen) == ["tcp/0.0.0.0:7448"]
    assert exposed_endpoints(["tcp/127.0.0.1:1", "tcp/[::1]:2", "unixsock-stream//x"]) == []


def test_a_daemon_warns_when_its_config_listens_beyond_loopback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    port = free_port(socket.SOCK_STREAM)
    path = tmp_path / "exposed.json5"
    path.write_text(json.dumps({"mode": "peer", "listen": {"endpoints": [f"tcp/0.0.0.0:{port}"]}}))
    with (
        caplog.at_level(logging.INFO, logger="qnav.contracts.transport"),
        open_session(ZenohSettings(config_file=str(path))),
    ):
        pass
    messages = [r.getMessage() for r in caplog.records]
    assert any("multicast scouting off" in m for m in messages)
    assert any("beyond loopback" in m and f"0.0.0.0:{port}" in m for m in messages)


# Per identity and key, refusals checked by order on one link rather than by waiting: a peer
# publishes the refused key, then a key it may publish, on one session whose publishers both
# know the listener's subscription (so both puts are sent to the hub); once the second arrives
# at the listener's single subscriber, the first would have arrived before it.


def _ready_publishers(session: Any, keys: list[str]) -> list[Any]:
    """Publishers on `keys`, once each has matched the listener's subscription."""
    publishers = [session.declare_publisher(k) for k in keys]
    deadline = time.monotonic() + 10
    while not all(p.matching_status.matching for p in publishers):
        assert time.monotonic() < deadline, f"no subscriber matched {keys}"
        time.sleep(0.01)
    return publishers


class Ordered:
    """Samples a listening identity receives, in arrival order (one subscriber: zenoh-python
    runs each subscriber's callback on its own thread, so two subscribers may reorder)."""

    def __init__(self, session: Any) -> None:
        self.arrived: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.subscriber = session.declare_subscriber(
            "**", lambda s: self.arrived.put((str(s.key_expr), bytes(s.payload.to_bytes())))
        )
        self.seen: list[tuple[str, bytes]] = []

    def has(self, key: str) -> bool:
        """Whether a sample of `key` has arrived (without waiting)."""
        with contextlib.suppress(queue.Empty):
            while True:
                self.seen.append(self.arrived.get_nowait())
        return any(k == key for k, _ in self.seen)

    def until(self, key: str, payload: bytes) -> list[tuple[str, bytes]]:
        """Every sample up to and including (key, payload), which must come within 10 s."""
        deadline = time.monotonic() + 10
        while (key, payload) not in self.seen:
            left = deadline - time.monotonic()
            assert left > 0, f"{key} {payload!r} never came; got {self.seen}"
            with contextlib.suppress(queue.Empty):
                self.seen.append(self.arrived.get(timeout=left))
        return self.seen


@pytest.mark.parametrize(
    ("identity", "refused", "allowed"),
    [
        ("operator", "cmd_vel", "qnav/estop_release"),
        ("operator", "qnav/vehicle_state", "qnav/vehicle_request"),
        ("operator", "car1/cmd_vel", "car1/qnav/estop_release"),
        ("sensors", "qnav/vehicle_request", "scan"),
        ("sensors", "cmd_vel", "pose"),
        ("sensors", "qnav/estop_release", "scan"),
        ("controller", "qnav/vehicle_request", "cmd_vel"),
        ("controller", "qnav/estop_release", "cmd_vel"),
        ("controller", "qnav/vehicle_state", "qnav/controller_status"),
        ("bridge", "cmd_vel", "qnav/vehicle_state"),
        ("bridge", "qnav/vehicle_request", "qnav/vehicle_state"),
        ("bridge", "car1/qnav/estop_release", "car1/qnav/vehicle_state"),
        ("server", "cmd_vel", "qnav/policy_announcement"),
        ("server", "qnav/estop_release", "car1/qnav/policy_announcement"),
        ("controller", "qnav/policy_announcement", "cmd_vel"),
        ("operator", "qnav/policy_announcement", "qnav/estop_release"),
    ],
)
def test_each_identity_is_refused_each_key_it_may_not_publish(
    certs: tuple[Path, str], hub: Any, identity: str, refused: str, allowed: str
) -> None:
    folder, _ = certs
    marker = f"{identity} on {allowed}".encode()
    with _session(folder, "recorder") as listener, _session(folder, identity) as session:
        heard = Ordered(listener)
        refuse, allow = _ready_publishers(session, [refused, allowed])
        refuse.put(wire.encode_json_msg({"arm": True}))
        allow.put(marker)
        seen = heard.until(allowed, marker)
    assert [k for k, _ in seen if k == refused] == []


def test_an_identity_allowed_to_publish_nothing_is_refused_every_key(
    certs: tuple[Path, str], hub: Any
) -> None:
    # The recorder is named by the rules, so it learns of subscribers and really sends (an
    # identity the rules do not name learns of none, and its client sends nothing at all).
    folder, _ = certs
    with (
        _session(folder, "bridge") as listener,
        _session(folder, "recorder") as recorder,
        _session(folder, "controller") as controller,
    ):
        heard = Ordered(listener)
        keys = [wire.key(t) for t in wire.TOPICS]
        for publisher in _ready_publishers(recorder, keys):
            publisher.put(b"recorder")
        # No allowed key to order by on the recorder's link: the controller's marker, put after
        # the recorder's puts left, bounds the wait instead.
        (status,) = _ready_publishers(controller, [wire.key(wire.CONTROLLER_STATUS)])
        time.sleep(0.2)
        status.put(b"after")
        seen = heard.until(wire.key(wire.CONTROLLER_STATUS), b"after")
    assert [k for k, payload in seen if payload == b"recorder"] == []


def test_a_certificate_of_another_authority_cannot_join(
    certs: tuple[Path, str], hub: Any, tmp_path: Path
) -> None:
    folder, _ = certs
    make_certificates(tmp_path, ("controller",))  # same name, an authority the hub does not trust
    config = json.loads((folder / "zenoh-controller.json5").read_text())
    tls = config["transport"]["link"]["tls"]
    tls["connect_certificate"] = str(tmp_path / "controller.pem")
    tls["connect_private_key"] = str(tmp_path / "controller-key.pem")
    config["connect"]["timeout_ms"] = 2000
    path = tmp_path / "zenoh-rogue.json5"
    path.write_text(json.dumps(config))
    with pytest.raises(ConfigError, match="cannot open a zenoh session"):
        open_session(ZenohSettings(config_file=str(path)))


def test_qnav_certs_signs_each_identity_by_name(certs: tuple[Path, str]) -> None:
    folder, _ = certs
    for name in IDENTITIES:
        cert = str(folder / f"{name}.pem")
        verified = subprocess.run(
            ["openssl", "verify", "-CAfile", str(folder / "ca.pem"), cert],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
        assert verified.returncode == 0, verified.stderr
        subject = subprocess.run(
            ["openssl", "x509", "-in", cert, "-noout", "-subject", "-ext", "subjectAltName"],
            capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
        assert f"CN = {name}" in subject and "127.0.0.1" in subject
        assert (folder / f"{name}-key.pem").stat().st_mode & 0o077 == 0


def test_qnav_certs_without_openssl_says_what_is_missing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("PATH", str(tmp_path / "nothing-here"))
    assert main(["certs", str(tmp_path / "certs")]) == 2
    assert "needs the openssl command" in capsys.readouterr().err


def test_the_bridge_daemon_runs_with_its_secure_config_and_only_the_controller_drives(
    certs: tuple[Path, str], hub: Any, tmp_path: Path
) -> None:
    folder, _ = certs
    forward = wire.encode_twist_msg(wire.Twist2D(0.5, 0.0))

    def throttles() -> list[int]:
        return [r.fields["chan3_raw"] for r in car.received("RC_CHANNELS_OVERRIDE")]

    with (
        MavlinkVehicle(vehicle_settings(free_port(socket.SOCK_DGRAM))) as car,
        _session(folder, "recorder") as listener,
    ):
        heard = Ordered(listener)
        port = car.settings.connection.rsplit(":", 1)[1]
        log = tmp_path / "bridge.log"
        with log.open("wb") as out:
            bridge = subprocess.Popen(
                [sys.executable, "-m", "qnav", "bridge",
                 "--set", f'zenoh.config_file="{folder / "zenoh-bridge.json5"}"',
                 "--set", f'mavlink.connection="udpout:127.0.0.1:{port}"'],
                stdout=out, stderr=out,
            )  # fmt: skip
        try:
            # Its state comes through the hub: the bridge's own publisher is allowed.
            wait_until(
                lambda: heard.has(wire.key(wire.VEHICLE_STATE)),
                timeout_s=60,
                what="the bridge's vehicle state through the secure hub",
            )
            # The operator's forward command is refused by the hub, its release is not: once
            # the release reached the recorder, the command would have reached the bridge.
            with _session(folder, "operator") as operator:
                command, release = _ready_publishers(
                    operator, [wire.key(wire.COMMAND), wire.key(wire.ESTOP_RELEASE)]
                )
                command.put(forward)
                release.put(wire.encode_bool_msg(True))
                heard.until(wire.key(wire.ESTOP_RELEASE), wire.encode_bool_msg(True))
                time.sleep(0.3)  # the bridge's next overrides go out every failsafe period
            assert set(throttles()) == {1500}, "a refused command moved the car"
            with _session(folder, "controller") as controller:
                (command,) = _ready_publishers(controller, [wire.key(wire.COMMAND)])
                wait_until(
                    lambda: command.put(forward) or any(t > 1500 for t in throttles()),
                    timeout_s=10,
                    what="the controller's command to reach the car",
                )
        finally:
            bridge.terminate()
            bridge.wait(timeout=20)
    assert "multicast scouting off" in log.read_text()
