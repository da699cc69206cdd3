"""Zenoh security: the shipped mutual-TLS + access-rules config, on loopback with real sessions.

A hub opens config/zenoh-secure.json5 (its TLS files pointed at certificates `qnav certs`
made); the other identities connect with the `[zenoh]` section `qnav certs` prints. Refusals
are checked by order on one link: a peer publishes the refused key first and a key it may
publish second, on the same session; once the second arrives, the first would have too.
"""

from __future__ import annotations

import json
import os
import queue
import socket
import subprocess
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from contracts import wire
from contracts.errors import ConfigError
from contracts.settings import from_dict
from contracts.transport import ZenohSettings, access_rules, open_session, zenoh_config
from qnav.certs import IDENTITIES, client_settings, make_certificates
from qnav.cli import main

ROOT = Path(__file__).resolve().parents[1]
SECURE = ROOT / "config" / "zenoh-secure.json5"
WAIT_S = 10.0
"""Deadline for a sample that must arrive (a loaded machine is slow, a refusal is not)."""


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _publishing_names() -> dict[str, tuple[str, ...]]:
    return {who: tuple(t.name for t in topics) for who, topics in wire.PUBLISHES.items()}


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("certs")
    assert main(["certs", str(folder)]) == 0
    return folder


def _hub_settings(certs: Path, endpoint: str) -> ZenohSettings:
    tls = "transport/link/tls"
    return ZenohSettings(
        config_file=str(SECURE),
        extra={
            "listen/endpoints": [endpoint],
            f"{tls}/root_ca_certificate": str(certs / "ca.pem"),
            f"{tls}/listen_certificate": str(certs / "router.pem"),
            f"{tls}/listen_private_key": str(certs / "router.key"),
            f"{tls}/connect_certificate": str(certs / "router.pem"),
            f"{tls}/connect_private_key": str(certs / "router.key"),
        },
    )


def _client(certs: Path, identity: str, endpoint: str) -> ZenohSettings:
    """Settings of `identity`, from the section `qnav certs` prints; fail fast, not retry."""
    section = tomllib.loads(client_settings(certs, identity, endpoint))["zenoh"]
    settings = from_dict(ZenohSettings, section)
    return ZenohSettings(
        connect=settings.connect, extra={**settings.extra, "connect/timeout_ms": 0}
    )


@pytest.fixture(scope="module")
def hub(certs: Path) -> Iterator[str]:
    endpoint = f"tls/127.0.0.1:{_free_port()}"
    with open_session(_hub_settings(certs, endpoint)):
        yield endpoint


class Listener:
    """A session of the bridge identity subscribed to every key, collecting (key, payload).

    One subscriber, so samples are seen in the order they arrive (zenoh-python runs each
    subscriber's callback on a thread of its own: two subscribers may reorder).
    """

    def __init__(self, certs: Path, endpoint: str) -> None:
        self.session = open_session(_client(certs, "bridge", endpoint))
        self.samples: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.subscriber = self.session.declare_subscriber("**", self._on_sample)
        self.seen: list[tuple[str, bytes]] = []

    def _on_sample(self, sample: Any) -> None:
        self.samples.put((str(sample.key_expr), bytes(sample.payload.to_bytes())))

    def wait_for(self, key: str, payload: bytes) -> list[tuple[str, bytes]]:
        """Every sample up to and including (key, payload); fails after WAIT_S."""
        deadline = time.monotonic() + WAIT_S
        while (key, payload) not in self.seen:
            left = deadline - time.monotonic()
            assert left > 0, f"{key} {payload!r} never arrived; got {self.seen}"
            try:
                self.seen.append(self.samples.get(timeout=left))
            except queue.Empty:
                continue
        return self.seen

    def close(self) -> None:
        self.session.close()


def _ready_publishers(session: Any, keys: list[str]) -> list[Any]:
    """Publishers on `keys`, once each knows the listener's subscription (so a put is sent
    to the hub, and only the hub's rules can stop it)."""
    publishers = [session.declare_publisher(k) for k in keys]
    deadline = time.monotonic() + WAIT_S
    while not all(p.matching_status.matching for p in publishers):
        assert time.monotonic() < deadline, f"no subscriber matched {keys}"
        time.sleep(0.01)
    return publishers


@pytest.fixture()
def listener(certs: Path, hub: str) -> Iterator[Listener]:
    made = Listener(certs, hub)
    yield made
    made.close()


def test_the_shipped_access_rules_are_made_from_the_publishes_table() -> None:
    import zenoh

    shipped = json.loads(zenoh.Config.from_file(str(SECURE)).get_json("access_control"))
    # Read both back through zenoh, which fills in the fields left out.
    made = zenoh.Config()
    made.insert_json5("access_control", json.dumps(access_rules(_publishing_names())))
    assert shipped == json.loads(made.get_json("access_control"))
    named = {s["id"] for s in shipped["subjects"]}
    assert named == set(wire.PUBLISHES) and set(wire.PUBLISHES) <= set(IDENTITIES)
    assert {t for topics in wire.PUBLISHES.values() for t in topics} == set(wire.TOPICS)


def test_the_shipped_config_is_mutual_tls_on_loopback_only() -> None:
    import zenoh

    config = zenoh.Config.from_file(str(SECURE))
    assert json.loads(config.get_json("listen/endpoints")) == ["tls/127.0.0.1:7447"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(config.get_json("access_control/default_permission")) == "deny"


def test_qnav_certs_makes_certificates_of_the_authority_named_by_identity(certs: Path) -> None:
    for identity in IDENTITIES:
        cert = certs / f"{identity}.pem"
        verify = subprocess.run(
            ["openssl", "verify", "-CAfile", str(certs / "ca.pem"), str(cert)],
            capture_output=True,
            text=True,
            check=False,
        )
        assert verify.returncode == 0, verify.stderr
        subject = subprocess.run(
            ["openssl", "x509", "-in", str(cert), "-noout", "-subject", "-ext", "subjectAltName"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        assert f"CN = {identity}" in subject and "127.0.0.1" in subject
        assert oct((certs / f"{identity}.key").stat().st_mode & 0o777) == "0o600"


def test_qnav_certs_without_openssl_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert main(["certs", str(tmp_path / "certs")]) == 2
    assert "needs the openssl command" in capsys.readouterr().err
    assert "PATH" in os.environ


def test_each_identity_delivers_what_it_publishes(
    certs: Path, hub: str, listener: Listener
) -> None:
    for identity, topics in wire.PUBLISHES.items():
        if not topics:
            continue
        with open_session(_client(certs, identity, hub)) as session:
            for publisher in _ready_publishers(session, [wire.key(t) for t in topics]):
                publisher.put(identity.encode())
            listener.wait_for(wire.key(topics[-1]), identity.encode())
        for topic in topics:
            assert (wire.key(topic), identity.encode()) in listener.seen, (identity, topic)
    # Under a namespace too (zenoh-bridge-ros2dds's `-n car1`).
    with open_session(_client(certs, "controller", hub)) as session:
        (namespaced,) = _ready_publishers(session, ["car1/cmd_vel"])
        namespaced.put(b"namespaced")
        listener.wait_for("car1/cmd_vel", b"namespaced")


@pytest.mark.parametrize(
    "case",
    [
        ("operator", wire.COMMAND, wire.ESTOP_RELEASE),
        ("sensors", wire.VEHICLE_REQUEST, wire.SCAN),
        ("sensors", wire.COMMAND, wire.POSE),
        ("sensors", wire.ESTOP_RELEASE, wire.SCAN),
        ("controller", wire.VEHICLE_REQUEST, wire.COMMAND),
        ("controller", wire.VEHICLE_STATE, wire.CONTROLLER_STATUS),
        ("bridge", wire.COMMAND, wire.VEHICLE_STATE),
    ],
)
def test_an_identity_cannot_publish_what_the_rules_do_not_allow_it(
    certs: Path, hub: str, listener: Listener, case: tuple[str, wire.Topic, wire.Topic]
) -> None:
    identity, refused, allowed = case
    marker = f"{identity}-{refused.name}".encode()
    with open_session(_client(certs, identity, hub)) as session:
        refuse, allow = _ready_publishers(session, [wire.key(refused), wire.key(allowed)])
        refuse.put(wire.encode_json_msg({"arm": True}))
        allow.put(marker)
        seen = listener.wait_for(wire.key(allowed), marker)
    assert [k for k, _ in seen if k == wire.key(refused)] == []


def test_the_recorder_identity_publishes_nothing(certs: Path, hub: str, listener: Listener) -> None:
    with open_session(_client(certs, "recorder", hub)) as recorder:
        request, command = _ready_publishers(
            recorder, [wire.key(wire.VEHICLE_REQUEST), wire.key(wire.COMMAND)]
        )
        request.put(wire.encode_json_msg({"arm": True}))
        command.put(b"drive")
        # The recorder's link has no allowed key to order by: a controller publishing after the
        # recorder's puts went out (they are sent when put returns) bounds the wait instead.
        with open_session(_client(certs, "controller", hub)) as controller:
            time.sleep(0.5)
            controller.put(wire.key(wire.CONTROLLER_STATUS), b"after")
            seen = listener.wait_for(wire.key(wire.CONTROLLER_STATUS), b"after")
    refused = (wire.key(wire.VEHICLE_REQUEST), wire.key(wire.COMMAND))
    assert [k for k, _ in seen if k in refused] == []


def test_a_peer_without_a_certificate_cannot_connect(certs: Path, hub: str) -> None:
    tls = "transport/link/tls"
    anonymous = ZenohSettings(
        connect=(hub,),
        extra={f"{tls}/root_ca_certificate": str(certs / "ca.pem"), "connect/timeout_ms": 0},
    )
    with pytest.raises(ConfigError, match="cannot open a zenoh session"):
        open_session(anonymous)
    plain_tcp = ZenohSettings(
        connect=(hub.replace("tls/", "tcp/"),), extra={"connect/timeout_ms": 0}
    )
    with pytest.raises(ConfigError, match="cannot open a zenoh session"):
        open_session(plain_tcp)


def test_a_certificate_of_another_authority_cannot_connect(
    certs: Path, hub: str, tmp_path: Path
) -> None:
    # Same common name, but signed by an authority the hub does not trust.
    make_certificates(tmp_path / "rogue", ("controller",))
    tls = "transport/link/tls"
    rogue = ZenohSettings(
        connect=(hub,),
        extra={
            f"{tls}/root_ca_certificate": str(certs / "ca.pem"),
            f"{tls}/connect_certificate": str(tmp_path / "rogue" / "controller.pem"),
            f"{tls}/connect_private_key": str(tmp_path / "rogue" / "controller.key"),
            f"{tls}/enable_mtls": True,
            "connect/timeout_ms": 0,
        },
    )
    with pytest.raises(ConfigError, match="cannot open a zenoh session"):
        open_session(rogue)


def test_the_hub_config_file_is_logged_and_local(
    certs: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("INFO", logger="contracts.transport")
    zenoh_config(_hub_settings(certs, "tls/127.0.0.1:7447"))
    assert "listening on tls/127.0.0.1:7447, multicast scouting off" in caplog.text
    assert "beyond loopback" not in caplog.text
