"""`qnav certs DIR`: a test certificate authority and one certificate per identity.

Zenoh's mutual TLS checks every peer's certificate against the authority, and its access rules
(config/zenoh-secure.json5) name identities by their certificate's common name. The files are
made with the `openssl` command; they are for tests and a first deployment: keep `ca.key`
off the car, and use your organisation's authority where there is one.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

from contracts.errors import ConfigError
from contracts.wire import PUBLISHES

IDENTITIES = ("router", *PUBLISHES)
"""Certificates made: the router (a zenohd hub) and every identity of the access rules."""

DAYS = 825
"""Validity of each certificate in days (the most some TLS clients accept)."""


def _openssl() -> str:
    found = shutil.which("openssl")
    if found is None:
        raise ConfigError(
            "qnav certs needs the openssl command, which is not on PATH "
            "(install it: apt-get install openssl)"
        )
    return found


def _run(arguments: Sequence[str]) -> None:
    done = subprocess.run(list(arguments), capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise ConfigError(f"{' '.join(arguments[:3])} ... failed: {done.stderr.strip()}")


def make_certificates(
    folder: Path, identities: Sequence[str] = IDENTITIES, hosts: Sequence[str] = ()
) -> dict[str, tuple[Path, Path]]:
    """Write ca.pem/ca.key and NAME.pem/NAME.key per identity; returns name -> (cert, key).

    Every certificate names 127.0.0.1 and localhost (and `hosts`) as its subject alternative
    names, so whichever process listens can be reached by those names with name checking on.
    An existing authority in `folder` is reused, so more identities can be added later.
    """
    openssl = _openssl()
    folder.mkdir(parents=True, exist_ok=True)
    ca_cert, ca_key = folder / "ca.pem", folder / "ca.key"
    if not (ca_cert.is_file() and ca_key.is_file()):
        _run(
            [
                *(openssl, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256"),
                *("-nodes", "-keyout", str(ca_key), "-out", str(ca_cert), "-days", str(DAYS)),
                *("-subj", "/CN=qnav test CA", "-addext", "basicConstraints=critical,CA:TRUE"),
                *("-addext", "keyUsage=critical,keyCertSign,cRLSign"),
            ]
        )
    names = ["IP:127.0.0.1", "DNS:localhost"] + [
        f"IP:{host}" if host.replace(".", "").isdigit() or ":" in host else f"DNS:{host}"
        for host in hosts
    ]
    made = {}
    for identity in identities:
        cert, key = folder / f"{identity}.pem", folder / f"{identity}.key"
        request = folder / f"{identity}.csr"
        extensions = folder / f"{identity}.ext"
        _run(
            [
                *(openssl, "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"),
                *("-keyout", str(key), "-out", str(request), "-subj", f"/CN={identity}"),
            ]
        )
        extensions.write_text(
            "basicConstraints=CA:FALSE\n"
            "keyUsage=critical,digitalSignature\n"
            "extendedKeyUsage=serverAuth,clientAuth\n"
            f"subjectAltName={','.join(names)}\n"
        )
        _run(
            [
                *(openssl, "x509", "-req", "-in", str(request), "-CA", str(ca_cert)),
                *("-CAkey", str(ca_key), "-CAcreateserial", "-out", str(cert)),
                *("-days", str(DAYS), "-extfile", str(extensions)),
            ]
        )
        request.unlink()
        extensions.unlink()
        key.chmod(0o600)
        made[identity] = (cert, key)
    ca_key.chmod(0o600)
    return made


def client_settings(folder: Path, identity: str, endpoint: str = "tls/127.0.0.1:7447") -> str:
    """The `[zenoh]` section of a daemon connecting to the secure hub as `identity`."""
    tls = "transport/link/tls"
    folder = folder.resolve()
    return (
        "[zenoh]\n"
        f'connect = ["{endpoint}"]\n'
        "extra = { "
        f'"{tls}/root_ca_certificate" = "{folder / "ca.pem"}", '
        f'"{tls}/connect_certificate" = "{folder / f"{identity}.pem"}", '
        f'"{tls}/connect_private_key" = "{folder / f"{identity}.key"}", '
        f'"{tls}/enable_mtls" = true }}\n'
    )


def run(args: argparse.Namespace) -> int:
    """The `qnav certs` verb."""
    folder: Path = args.folder
    identities = tuple(args.identity or IDENTITIES)
    made = make_certificates(folder, identities, tuple(args.host or ()))
    print(f"authority: {folder / 'ca.pem'} (keep {folder / 'ca.key'} off the car)")
    for identity, (cert, key) in made.items():
        print(f"{identity}: {cert} {key}")
    print("\nA daemon joins the hub (config/zenoh-secure.json5) as the controller with:")
    print(client_settings(folder, "controller"))
    return 0
