"""The policy delivery contract: announcements, chunk keys, signatures, contract fit."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from qnav.contracts import delivery, wire
from qnav.contracts.errors import ConfigError
from qnav.contracts.policy_file import ActionVelocity, PolicyContract
from qnav.controller.onnx_file import read_onnx
from tests.conftest import PolicyFactory


def contract_of(path: Path) -> PolicyContract:
    return PolicyContract.from_metadata(read_onnx(path).metadata, str(path))


@pytest.fixture(scope="module")
def key_pair() -> tuple[Any, Any]:
    private, public = delivery.generate_key_pair()
    from cryptography.hazmat.primitives import serialization

    return (
        serialization.load_pem_private_key(private, password=None),
        serialization.load_pem_public_key(public),
    )


@pytest.fixture
def announcement(make_policy: PolicyFactory, key_pair: tuple[Any, Any]) -> delivery.Announcement:
    path = make_policy()
    return delivery.make_announcement(
        path.read_bytes(), "run 7/policy", contract_of(path), key_pair[0], 16384
    )


def test_an_announcement_survives_the_wire_and_verifies_with_its_key(
    announcement: delivery.Announcement, key_pair: tuple[Any, Any]
) -> None:
    back = delivery.decode_announcement(delivery.encode_announcement(announcement))
    assert back == announcement
    assert back.version == f"run-7-policy-{announcement.sha256[:12]}"
    assert back.chunks == -(-announcement.size_bytes // 16384)
    assert delivery.verify(key_pair[1], back)


def test_a_signature_verifies_for_nothing_but_what_was_signed(
    announcement: delivery.Announcement, key_pair: tuple[Any, Any]
) -> None:
    public = key_pair[1]
    _, other_public = delivery.generate_key_pair()
    assert not delivery.verify(
        public, replace(announcement, sha256=delivery.sha256_of(b"another file"))
    )
    assert not delivery.verify(public, replace(announcement, version="other-000000000000"))
    assert not delivery.verify(
        public, replace(announcement, size_bytes=announcement.size_bytes + 1)
    )
    from cryptography.hazmat.primitives import serialization

    stranger = serialization.load_pem_public_key(other_public)
    assert not delivery.verify(stranger, announcement)


def _tampered(announcement: delivery.Announcement, **changes: Any) -> bytes:
    value = announcement.to_json() | changes
    return wire.encode_json_msg(value)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"format": "qnav-policy-announcement/9"}, "format"),
        ({"version": "../etc"}, "version"),
        ({"version": "a/*"}, "version"),
        ({"sha256": "00"}, "sha256"),
        ({"signature": "zz" * 64}, "signature"),
        ({"size_bytes": 0}, "size_bytes"),
        ({"size_bytes": 10**12}, "size_bytes"),
        ({"size_bytes": True}, "size_bytes"),
        ({"chunk_bytes": 10**9}, "chunk_bytes"),
        ({"contract": []}, "contract"),
        ({"contract": {"num_beams": 720}}, "contract"),
        ({"evaluation": {"success": "high"}}, "evaluation"),
    ],
)
def test_a_malformed_announcement_is_refused_with_what_is_wrong(
    announcement: delivery.Announcement, changes: dict[str, Any], match: str
) -> None:
    with pytest.raises(wire.WireError, match=match):
        delivery.decode_announcement(_tampered(announcement, **changes))


@pytest.mark.parametrize("payload", [b"", b"\x00\x01\x00\x00garbage", b"\x00\x01\x00\x00" * 3])
def test_garbage_is_no_announcement(payload: bytes) -> None:
    with pytest.raises(wire.WireError):
        delivery.decode_announcement(payload)


def test_chunk_keys_round_trip_and_nothing_else_parses_as_one() -> None:
    assert delivery.parse_chunk_key(delivery.chunk_key("p-1", 3)) == ("p-1", 3)
    assert delivery.parse_chunk_key(delivery.chunk_key("p-1", 3, "car1"), "car1") == ("p-1", 3)
    for key in (
        "qnav/policy_file/p-1",
        "qnav/policy_file/p-1/x",
        "other/p-1/3",
        "qnav/policy_file/*/3",
    ):
        assert delivery.parse_chunk_key(key) is None


def test_a_policy_must_keep_the_cars_beams_actions_period_and_dynamics(
    make_policy: PolicyFactory,
) -> None:
    running = contract_of(make_policy())
    assert delivery.contract_mismatch(running, contract_of(make_policy(seed=1))) is None
    assert (
        delivery.contract_mismatch(running, replace(running, window_length=3, state_slots=2))
        is None
    )
    faster = (ActionVelocity(2.0, 0.0), *running.actions[1:])
    for changed, name in (
        (replace(running, num_beams=360), "num_beams"),
        (replace(running, actions=faster), "actions"),
        (replace(running, control_period_s=0.05), "control_period_s"),
        (replace(running, dynamics="increment"), "dynamics"),
    ):
        why = delivery.contract_mismatch(running, changed)
        assert why is not None and why.startswith(f"contract {name} is"), why


def test_keys_that_are_not_ed25519_name_the_setting(tmp_path: Path) -> None:
    path = tmp_path / "not-a-key.pem"
    path.write_text("hello")
    with pytest.raises(ConfigError, match=r"policy\.public_key = .*not a readable public key"):
        delivery.load_public_key(path, "policy.public_key")
    with pytest.raises(ConfigError, match="--key"):
        delivery.load_private_key(tmp_path / "missing.key", "--key")
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    other = ec.generate_private_key(ec.SECP256R1()).public_key()
    path.write_bytes(
        other.public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
        )
    )
    with pytest.raises(ConfigError, match="not an Ed25519 key"):
        delivery.load_public_key(path, "policy.public_key")


def test_openssl_made_keys_work_too(tmp_path: Path, announcement: delivery.Announcement) -> None:
    """docs/serve.md's commands for making the key pair without qnav."""
    import shutil
    import subprocess

    if shutil.which("openssl") is None:
        pytest.skip("no openssl command")
    private, public = tmp_path / "k.pem", tmp_path / "k.pub"
    subprocess.run(
        ["openssl", "genpkey", "-algorithm", "ed25519", "-out", str(private)], check=True
    )
    subprocess.run(
        ["openssl", "pkey", "-in", str(private), "-pubout", "-out", str(public)], check=True
    )
    key = delivery.load_private_key(private, "--key")
    signed = replace(
        announcement,
        signature=delivery.sign(
            key, announcement.version, announcement.sha256, announcement.size_bytes
        ),
    )
    assert delivery.verify(delivery.load_public_key(public, "policy.public_key"), signed)
    assert json.loads(json.dumps(signed.to_json()))["signature"] == signed.signature
