"""Policy delivery: how `qnav serve` (the desktop) hands policy files to the car's controller.

Two zenoh keys, both under the optional namespace (`contracts.wire.key`):

- `POLICY_ANNOUNCEMENT` (`qnav/policy_announcement`, a std_msgs/String holding one JSON
  object): the server puts the policy it recommends there when it changes, and again every
  few seconds, so a car that joins late hears it. `Announcement` is its content: the version,
  the file's sha256 and size, how it is cut into chunks, an Ed25519 signature, the contract the
  policy was trained with and its test figures.
- `POLICY_FILE` (`qnav/policy_file`): a queryable; `get("qnav/policy_file/VERSION/INDEX")`
  returns chunk INDEX (from 0) of that version's file as raw bytes.

The signature covers `signed_bytes(version, sha256, size)`; the sha256 covers the file, and the
file carries its own contract in its metadata, so a car that verified the signature and the
hash trusts the file's contract, not the announcement's copy (which only lets it refuse an
unfit policy before fetching it). Keys are Ed25519 (`qnav keys`, or openssl, docs/serve.md):
the desktop holds the private key, the car only the public one.

This module imports `cryptography` only where a key is loaded or used.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from qnav.contracts import wire
from qnav.contracts.errors import ConfigError, PolicyFileError
from qnav.contracts.policy_file import METADATA_PREFIX, PolicyContract

POLICY_ANNOUNCEMENT = wire.POLICY_ANNOUNCEMENT
"""Where the server announces the policy it recommends (JSON, `Announcement`)."""

POLICY_FILE = "qnav/policy_file"
"""Prefix of the queryable that returns chunks of policy files: `POLICY_FILE/VERSION/INDEX`."""

ANNOUNCEMENT_FORMAT = "qnav-policy-announcement/1"
"""Value of an announcement's `format` field."""

SIGNATURE_DOMAIN = "qnav-policy-signature/1"
"""First line of the signed bytes, so a qnav policy signature means nothing anywhere else."""

DEFAULT_CHUNK_BYTES = 256 * 1024
"""Chunk size the server cuts files into (a paper-sized float32 file is 28 chunks)."""

MAX_CHUNK_BYTES = 4 * 1024 * 1024
"""Largest chunk an announcement may declare (a larger one is malformed)."""

MAX_FILE_BYTES = 256 * 1024 * 1024
"""Largest policy file an announcement may declare (a larger one is malformed)."""

_VERSION = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
"""A version: a zenoh key chunk without wildcards or separators."""

_SHA256 = re.compile(r"[0-9a-f]{64}")


def sha256_of(data: bytes) -> str:
    """The hex sha256 of `data`."""
    return hashlib.sha256(data).hexdigest()


def version_of(name: str, sha256: str) -> str:
    """A policy version: the file's name (reduced to key-safe characters) and its hash's first
    12 hex digits, so two different files never share a version."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-._")[:60] or "policy"
    return f"{stem}-{sha256[:12]}"


def version_of_file(path: Path) -> str:
    """The version of a local policy file (as `version_of` names it by the file's stem)."""
    return version_of(Path(path).stem, sha256_of(Path(path).read_bytes()))


def signed_bytes(version: str, sha256: str, size_bytes: int) -> bytes:
    """What the signature signs."""
    return f"{SIGNATURE_DOMAIN}\n{version}\n{sha256}\n{size_bytes}\n".encode()


def chunk_key(version: str, index: int, namespace: str = "") -> str:
    """The key to `get` chunk `index` of `version` at."""
    return wire.key(f"{POLICY_FILE}/{version}/{index}", namespace)


def parse_chunk_key(key: str, namespace: str = "") -> tuple[str, int] | None:
    """(version, index) of a chunk key, or None if it is not one."""
    prefix = wire.key(POLICY_FILE, namespace) + "/"
    if not key.startswith(prefix):
        return None
    version, _, index = key[len(prefix) :].partition("/")
    if not _VERSION.fullmatch(version) or not index.isdigit() or len(index) > 9:
        return None
    return version, int(index)


@dataclass(frozen=True)
class Announcement:
    """One announcement of a policy file (module docstring)."""

    version: str
    """Version name (`version_of`)."""
    sha256: str
    """Hex sha256 of the whole file."""
    size_bytes: int
    """File size."""
    chunk_bytes: int
    """Size of every chunk but the last."""
    signature: str
    """Hex Ed25519 signature of `signed_bytes(version, sha256, size_bytes)`."""
    contract: PolicyContract
    """The contract in the file's metadata (a copy: the file's own is what counts)."""
    evaluation: dict[str, float] = field(default_factory=dict)
    """The file's test figures (its contract's evaluation)."""
    format: str = ANNOUNCEMENT_FORMAT
    """Announcement layout version."""

    @property
    def chunks(self) -> int:
        """Number of chunks."""
        return max(1, math.ceil(self.size_bytes / self.chunk_bytes))

    def to_json(self) -> dict[str, Any]:
        """As one JSON object."""
        contract = asdict(self.contract)
        contract.pop("evaluation")
        return {
            "format": self.format,
            "version": self.version,
            "sha256": self.sha256,
            "size_bytes": self.size_bytes,
            "chunk_bytes": self.chunk_bytes,
            "chunks": self.chunks,
            "signature": self.signature,
            "contract": contract,
            "evaluation": dict(self.evaluation),
        }


def encode_announcement(announcement: Announcement) -> bytes:
    """The payload put on `POLICY_ANNOUNCEMENT`."""
    return wire.encode_json_msg(announcement.to_json())


def decode_announcement(payload: bytes) -> Announcement:
    """An announcement; `WireError` if it is not a well-formed one (its signature is not
    checked here: `verify`)."""
    value = wire.decode_json_msg(payload)
    if value.get("format") != ANNOUNCEMENT_FORMAT:
        raise wire.WireError(
            f"announcement format {value.get('format')!r}; this controller reads "
            f"{ANNOUNCEMENT_FORMAT!r}"
        )
    version, sha, signature = value.get("version"), value.get("sha256"), value.get("signature")
    size, chunk = value.get("size_bytes"), value.get("chunk_bytes")
    if not isinstance(version, str) or not _VERSION.fullmatch(version):
        raise wire.WireError(f"announcement version {version!r} is not a version name")
    if not isinstance(sha, str) or not _SHA256.fullmatch(sha):
        raise wire.WireError("announcement sha256 is not 64 lower-case hex digits")
    if not isinstance(signature, str) or not re.fullmatch(r"[0-9a-f]{128}", signature):
        raise wire.WireError("announcement signature is not 128 lower-case hex digits")
    if type(size) is not int or not 0 < size <= MAX_FILE_BYTES:
        raise wire.WireError(f"announcement size_bytes {size!r} is not in [1, {MAX_FILE_BYTES}]")
    if type(chunk) is not int or not 0 < chunk <= MAX_CHUNK_BYTES:
        raise wire.WireError(f"announcement chunk_bytes {chunk!r} is not in [1, {MAX_CHUNK_BYTES}]")
    contract_json, evaluation = value.get("contract"), value.get("evaluation", {})
    if not isinstance(contract_json, dict) or not isinstance(evaluation, dict):
        raise wire.WireError("announcement contract or evaluation is not a JSON object")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in evaluation.values()):
        raise wire.WireError("announcement evaluation holds values that are not numbers")
    metadata = {METADATA_PREFIX + k: json.dumps(v) for k, v in contract_json.items()}
    metadata.setdefault(METADATA_PREFIX + "evaluation", json.dumps(evaluation))
    try:
        contract = PolicyContract.from_metadata(metadata, f"announced policy {version}")
    except (PolicyFileError, TypeError, ValueError, KeyError) as error:
        raise wire.WireError(f"announcement contract: {error}") from None
    return Announcement(version, sha, size, chunk, signature, contract, dict(evaluation))


# ---- keys and signatures ---------------------------------------------------------------------

PRIVATE_KEY_FILE = "policy-signing.key"
"""Name `qnav keys` gives the private key (PEM, PKCS#8): it stays on the desktop."""

PUBLIC_KEY_FILE = "policy-signing.pub"
"""Name `qnav keys` gives the public key (PEM, SubjectPublicKeyInfo): the car's copy."""


def generate_key_pair() -> tuple[bytes, bytes]:
    """A new Ed25519 key pair as PEM: (private, public)."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    key = Ed25519PrivateKey.generate()
    private = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    public = key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    return private, public


def load_private_key(path: Path, setting: str) -> Any:
    """The Ed25519 private key in the PEM file `path`; `ConfigError` naming `setting` if not."""
    return _load_pem_key(path, setting, private=True)


def load_public_key(path: Path, setting: str) -> Any:
    """The Ed25519 public key in the PEM file `path`; `ConfigError` naming `setting` if not."""
    return _load_pem_key(path, setting, private=False)


def _load_pem_key(path: Path, setting: str, *, private: bool) -> Any:
    """The one PEM reader of both keys (the server's private one, the car's public one)."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import (
        Ed25519PrivateKey,
        Ed25519PublicKey,
    )

    kind = "private" if private else "public"
    try:
        data = Path(path).read_bytes()
        if private:
            key: Any = serialization.load_pem_private_key(data, password=None)
        else:
            key = serialization.load_pem_public_key(data)
    except (OSError, ValueError, TypeError) as error:
        why = f"not a readable {kind} key ({error})"
        raise ConfigError(f"{setting} = {str(path)!r}: {why}") from None
    if not isinstance(key, Ed25519PrivateKey if private else Ed25519PublicKey):
        raise ConfigError(f"{setting} = {str(path)!r}: not an Ed25519 key")
    return key


def sign(private_key: Any, version: str, sha256: str, size_bytes: int) -> str:
    """The hex signature of a policy file's version, hash and size."""
    return bytes(private_key.sign(signed_bytes(version, sha256, size_bytes))).hex()


def verify(public_key: Any, announcement: Announcement) -> bool:
    """Whether the announcement's signature is the key's signature of its version, hash, size."""
    from cryptography.exceptions import InvalidSignature

    try:
        public_key.verify(
            bytes.fromhex(announcement.signature),
            signed_bytes(announcement.version, announcement.sha256, announcement.size_bytes),
        )
    except (InvalidSignature, ValueError):
        return False
    return True


def make_announcement(
    data: bytes, name: str, contract: PolicyContract, private_key: Any, chunk_bytes: int
) -> Announcement:
    """The signed announcement of the policy file `data` (named `name`, holding `contract`)."""
    sha = sha256_of(data)
    version = version_of(name, sha)
    return Announcement(
        version=version,
        sha256=sha,
        size_bytes=len(data),
        chunk_bytes=chunk_bytes,
        signature=sign(private_key, version, sha, len(data)),
        contract=contract,
        evaluation=dict(contract.evaluation),
    )


CONTRACT_FIELDS_KEPT = ("num_beams", "actions", "control_period_s", "dynamics")
"""What a delivered policy must share with the running one: the car's sensors (beams), what its
actions command, the control period the loop keeps, the dynamics the car has. The window, the
network and its weights may change."""


def contract_mismatch(running: PolicyContract, candidate: PolicyContract) -> str | None:
    """Why `candidate` cannot replace `running` on this car, or None if it can."""
    for name in CONTRACT_FIELDS_KEPT:
        have, offered = getattr(running, name), getattr(candidate, name)
        if have != offered:
            return f"contract {name} is {_brief(offered)}; this car runs {_brief(have)}"
    return None


def _brief(value: Any) -> str:
    if isinstance(value, tuple):
        pairs = (f"({a.linear_mps:g} m/s, {a.angular_radps:g} rad/s)" for a in value)
        return "[" + ", ".join(pairs) + "]"
    return repr(value)
