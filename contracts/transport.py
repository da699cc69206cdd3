"""Zenoh session settings shared by every daemon (controller, bridge, sim-car, recorder).

Defaults keep a session on this machine: listen on a loopback endpoint or connect to one, with
multicast scouting off, so nothing is exposed or discovered by accident. A zenoh configuration
file, when given, is used as is (TLS, access control, routers): mode, endpoints and scouting
then come from it, and only `extra` is applied over it; but listen endpoints and multicast
scouting it leaves unset stay local (loopback, off) rather than zenoh's defaults (every
interface, on), and what the session then exposes is logged at start.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from contracts.errors import ConfigError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where the first daemon listens and the others connect, unless configured otherwise."""


@dataclass(frozen=True)
class ZenohSettings:
    """How a daemon joins the zenoh network."""

    SECTION = "zenoh"

    mode: Literal["auto", "peer", "client", "router"] = "auto"
    """Zenoh session mode; auto: peer when listening (a hub others connect to), else client
    (a client's traffic is routed through the peer or router it connects to; two peers that
    only connect to a hub do not hear each other)."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on, e.g. tcp/127.0.0.1:7447 (none: listen nowhere)."""
    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Endpoints to connect to (a router, or a peer that listens)."""
    multicast_scouting: bool = False
    """Discover peers by UDP multicast (off: only the endpoints above are used)."""
    namespace: str = ""
    """Prefix of every key, as zenoh-bridge-ros2dds's namespace (e.g. car1)."""
    config_file: str = ""
    """A zenoh JSON5 configuration file used as is (mode, endpoints, scouting come from it;
    listening and multicast scouting it leaves unset stay loopback and off)."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Further zenoh settings by path, e.g. {"transport/unicast/lowlatency" = true}."""

    def __post_init__(self) -> None:
        if self.mode not in ("auto", "peer", "client", "router"):
            raise ConfigError(
                f"zenoh.mode = {self.mode!r} is not one of auto, peer, client, router"
            )
        if self.mode == "client" and self.listen:
            raise ConfigError("zenoh.listen: a client cannot listen; use mode = peer or auto")
        for name in ("listen", "connect"):
            for endpoint in getattr(self, name):
                if "/" not in endpoint:
                    raise ConfigError(
                        f"zenoh.{name} endpoint {endpoint!r} is not of the form "
                        "PROTOCOL/ADDRESS:PORT (e.g. tcp/127.0.0.1:7447)"
                    )
        if self.config_file and not Path(self.config_file).is_file():
            raise ConfigError(f"zenoh.config_file {self.config_file!r} does not exist")

    @property
    def session_mode(self) -> str:
        """The mode the session opens in (auto resolved)."""
        if self.mode != "auto":
            return self.mode
        return "peer" if self.listen else "client"


def zenoh_config(settings: ZenohSettings) -> Any:
    """A `zenoh.Config` for these settings."""
    import zenoh

    if settings.config_file:
        try:
            config = zenoh.Config.from_file(settings.config_file)
        except Exception as error:  # zenoh raises its own error type
            raise ConfigError(f"zenoh.config_file {settings.config_file!r}: {error}") from None
        _guard_file_config(config, settings.config_file)
    else:
        config = zenoh.Config()
        config.insert_json5("mode", json.dumps(settings.session_mode))
        config.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
        config.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
        config.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
        if settings.session_mode == "client":
            # A client needs its router (or listening peer) to open: keep trying rather than
            # fail, so daemons may start in any order.
            config.insert_json5("connect/timeout_ms", "-1")
    for path, value in settings.extra.items():
        try:
            config.insert_json5(path, json.dumps(value))
        except Exception as error:  # zenoh raises its own error type
            raise ConfigError(f"zenoh.extra[{path!r}] = {value!r} is refused: {error}") from None
    return config


LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")
"""Endpoint protocols that never leave the machine."""


def is_loopback(endpoint: str) -> bool:
    """Whether a zenoh endpoint (PROTOCOL/ADDRESS:PORT) is reachable only from this machine."""
    protocol, _, address = endpoint.partition("/")
    if protocol in LOCAL_PROTOCOLS:
        return True
    host = address.split("?")[0].split("#")[0].rsplit(":", 1)[0].strip("[]").lower()
    return host in {"localhost", "::1"} or host.startswith("127.")


def loopback_default(mode: str) -> list[str]:
    """Where a file that names no listen endpoints listens: zenoh's defaults, on loopback only
    (zenoh's own listen on every interface)."""
    if mode == "router":
        return ["tcp/127.0.0.1:7447"]
    return ["tcp/127.0.0.1:0"] if mode == "peer" else []


def _json_setting(config: Any, path: str) -> Any:
    return json.loads(config.get_json(path))


def _guard_file_config(config: Any, path: str) -> None:
    """Default what a user's file leaves unset to local-only, and log what the session exposes.

    Zenoh's own defaults listen on every interface and scout by multicast; a file that does not
    name them would silently do both. Set explicitly, the file's values are kept (with a warning
    when they reach beyond this machine).
    """
    log = logging.getLogger(__name__)
    mode = _json_setting(config, "mode") or "peer"
    notes = []
    listen = _json_setting(config, "listen/endpoints")
    if not isinstance(listen, list):  # unset: zenoh's per-mode defaults
        listen = loopback_default(mode)
        config.insert_json5("listen/endpoints", json.dumps(listen))
        notes.append("listen endpoints unset in the file: loopback only")
    multicast = _json_setting(config, "scouting/multicast/enabled")
    if multicast is None:
        multicast = False
        config.insert_json5("scouting/multicast/enabled", "false")
        notes.append("multicast scouting unset in the file: off")
    log.info(
        "zenoh: config file %s: mode %s, listening on %s, multicast scouting %s%s",
        path,
        mode,
        ", ".join(listen) or "nothing",
        "on" if multicast else "off",
        f" ({'; '.join(notes)})" if notes else "",
    )
    exposed = [endpoint for endpoint in listen if not is_loopback(endpoint)]
    if exposed:
        log.warning(
            "zenoh: listening beyond loopback on %s: other machines can reach this session "
            "(use TLS with access rules, docs/deploy.md 'Securing zenoh')",
            ", ".join(exposed),
        )
    if multicast:
        log.warning("zenoh: multicast scouting is on: this session announces itself on the LAN")


def open_session(settings: ZenohSettings) -> Any:
    """An open zenoh session (close it, or use it in a `with` block)."""
    import zenoh

    if settings.session_mode == "client" and not settings.config_file:
        logging.getLogger(__name__).info(
            "zenoh: connecting to %s (waiting until something listens there)",
            ", ".join(settings.connect),
        )
    try:
        return zenoh.open(zenoh_config(settings))
    except Exception as error:
        raise ConfigError(
            f"cannot open a zenoh session (listen {list(settings.listen)}, "
            f"connect {list(settings.connect)}): {error}"
        ) from None


def access_rules(publishes: dict[str, tuple[str, ...]]) -> dict[str, Any]:
    """Zenoh `access_control` allowing each identity to publish only its keys.

    `publishes` maps a certificate common name to topic names. Every key is also allowed under
    any namespace (`**/name` matches `name` and `car1/name`). Anything else a remote sends is
    refused (default deny); subscribing, and the hub forwarding publications out, stay open.
    """
    rules: list[dict[str, Any]] = [
        {
            "id": "subscribe",
            "messages": ["declare_subscriber"],
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": ["**"],
        },
        {
            "id": "deliver",
            "messages": ["put"],
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": ["**"],
        },
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for identity, names in publishes.items():
        subjects.append({"id": identity, "cert_common_names": [identity]})
        granted = ["subscribe", "deliver"]
        if names:
            rules.append(
                {
                    "id": f"{identity}-publishes",
                    "messages": ["put"],
                    "flows": ["ingress"],
                    "permission": "allow",
                    "key_exprs": [f"**/{name}" for name in names],
                }
            )
            granted.append(f"{identity}-publishes")
        policies.append({"id": identity, "rules": granted, "subjects": [identity]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
