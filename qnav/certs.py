"""`qnav certs`: a test certificate authority and one certificate per identity, for zenoh's
mutual TLS and access control (config/zenoh-secure.json5, docs/deploy.md).

It runs the `openssl` command line tool; the same commands, shown by `--print-commands`, make
the certificates by hand. Each identity's certificate carries its name as the common name (what
zenoh's access control matches, `cert_common_names`) and `localhost` / `127.0.0.1` as
alternative names, and is good for both ends of a TLS connection. For a real car, make the CA
on a machine you trust and copy only each identity's own key to it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
from pathlib import Path

from qnav.contracts.errors import ConfigError
from qnav.contracts.transport import secure_client_config, secure_hub_config
from qnav.contracts.wire import PUBLISHERS
from qnav.verbs.parser import Verbs, flag, verb

IDENTITIES = ("hub", "controller", "bridge", "recorder", "sensors", "operator", "server")
"""The identities of config/zenoh-secure.json5: the listening hub, each daemon, the sensors
(lidar and motion capture, or the sim-car), the operator who may arm and release, and the
policy server (`qnav serve`, docs/serve.md)."""

DAYS = 825
"""Validity of the certificates (the most that common TLS clients accept)."""


def commands(folder: Path, names: tuple[str, ...]) -> list[list[str]]:
    """The openssl commands that make `folder`/ca.pem and NAME.pem / NAME-key.pem per name."""
    ca_key, ca = folder / "ca-key.pem", folder / "ca.pem"
    steps = [
        ["openssl", "ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", str(ca_key)],
        ["openssl", "req", "-x509", "-new", "-key", str(ca_key), "-sha256", "-days", str(DAYS),
         "-subj", "/CN=qnav test CA", "-out", str(ca)],
    ]  # fmt: skip
    for name in names:
        key, request, cert = (folder / f"{name}{s}" for s in ("-key.pem", ".csr", ".pem"))
        extensions = folder / f"{name}.ext"
        steps += [
            ["openssl", "ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", str(key)],
            ["openssl", "req", "-new", "-key", str(key), "-subj", f"/CN={name}",
             "-out", str(request)],
            ["openssl", "x509", "-req", "-in", str(request), "-CA", str(ca), "-CAkey", str(ca_key),
             "-CAcreateserial", "-days", str(DAYS), "-sha256", "-extfile", str(extensions),
             "-out", str(cert)],
        ]  # fmt: skip
    return steps


EXTENSIONS = (
    "basicConstraints = CA:FALSE\n"
    "keyUsage = digitalSignature, keyEncipherment\n"
    "extendedKeyUsage = serverAuth, clientAuth\n"
    "subjectAltName = DNS:localhost, IP:127.0.0.1\n"
)
"""X.509 extensions of every identity's certificate."""


def files_written(folder: Path, names: tuple[str, ...]) -> list[Path]:
    """Every file `qnav certs` writes into `folder`, the ones it removes after use included."""
    per_name = ("-key.pem", ".pem", ".csr", ".ext")
    return [
        *(folder / name for name in ("ca-key.pem", "ca.pem", "ca.srl", "zenoh-hub.json5")),
        *(folder / f"{name}{suffix}" for name in names for suffix in per_name),
        *(folder / f"zenoh-{name}.json5" for name in names if name != "hub"),
    ]


def prepare_folder(folder: Path, names: tuple[str, ...], force: bool = False) -> None:
    """Create `folder`, or refuse (ConfigError) when it is a file, cannot be created, or holds
    files `qnav certs` would write (unless `force`): a CA key overwritten by accident leaves
    every daemon's certificate unverifiable."""
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"{folder} exists and is not a folder")
    existing = [path.name for path in files_written(folder, names) if path.exists()]
    if existing and not force:
        raise ConfigError(
            f"{folder} already holds {', '.join(existing)}; --force replaces them (every "
            "daemon then needs its new certificate)"
        )
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"cannot create the folder {folder}: {error.strerror}") from None


def make_certificates(
    folder: Path, names: tuple[str, ...] = IDENTITIES, force: bool = False
) -> list[Path]:
    """Make the CA and the identities' certificates in `folder` (refused as `prepare_folder`
    says); returns the certificates."""
    if shutil.which("openssl") is None:
        raise ConfigError("needs the openssl command (apt install openssl)")
    prepare_folder(folder, names, force)
    for name in names:
        (folder / f"{name}.ext").write_text(EXTENSIONS)
    for step in commands(folder, names):
        done = subprocess.run(step, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise ConfigError(f"{' '.join(step)} failed: {done.stderr.strip()}")
    for name in names:
        (folder / f"{name}.csr").unlink()
        (folder / f"{name}.ext").unlink()
        (folder / f"{name}-key.pem").chmod(0o600)
    (folder / "ca-key.pem").chmod(0o600)
    return [folder / "ca.pem", *(folder / f"{name}.pem" for name in names)]


def write_zenoh_configs(folder: Path, endpoint: str, names: tuple[str, ...]) -> list[Path]:
    """`zenoh-hub.json5` (the hub: mutual TLS and access control) and `zenoh-NAME.json5` per
    daemon identity, each naming the certificates in `folder` by absolute path."""
    publishers = {name: tuple(t.name for t in topics) for name, topics in PUBLISHERS.items()}
    cert_dir = str(folder.resolve())
    written = [folder / "zenoh-hub.json5"]
    written[0].write_text(json.dumps(secure_hub_config(cert_dir, endpoint, publishers), indent=2))
    for name in names:
        if name == "hub":
            continue
        path = folder / f"zenoh-{name}.json5"
        path.write_text(json.dumps(secure_client_config(cert_dir, name, endpoint), indent=2))
        written.append(path)
    return written


def certs_verb(args: argparse.Namespace) -> int:
    """Handler of `qnav certs`."""
    names = tuple(args.names or IDENTITIES)
    if args.print_commands:
        for step in commands(args.folder, names):
            print(" ".join(step))
        return 0
    try:
        written = make_certificates(args.folder, names, force=args.force)
        written += write_zenoh_configs(args.folder, args.endpoint, names)
    except OSError as error:
        raise ConfigError(f"cannot write into {args.folder}: {error}") from None
    for path in written:
        print(f"wrote {path}")
    return 0


def add_verbs(verbs: Verbs) -> None:
    """`qnav certs`: its options."""
    _add_certs(verbs)


def _add_certs(verbs: Verbs) -> None:
    """`qnav certs FOLDER`."""
    parser = verb(
        verbs,
        certs_verb,
        "certs",
        help="a test CA and a certificate per identity, for zenoh's mutual TLS",
    )
    parser.add_argument("folder", type=Path, help="where to write them (e.g. certs/)")
    parser.add_argument(
        "--names",
        nargs="+",
        help="identities (default: hub controller bridge recorder sensors operator server)",
    )
    parser.add_argument(
        "--endpoint",
        default="tls/127.0.0.1:7447",
        help="the hub's TLS endpoint written into the zenoh configs (tls/127.0.0.1:7447)",
    )
    flag(parser, "--print-commands", "print the openssl commands, run nothing")
    flag(parser, "--force", "replace the certificates and keys already in FOLDER")
