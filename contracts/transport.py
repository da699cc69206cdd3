"""Zenoh session settings shared by every daemon (controller, bridge, sim-car, recorder).

Defaults keep a session on this machine: listen on a loopback endpoint or connect to one, with
multicast scouting off, so nothing is exposed or discovered by accident. A zenoh configuration
file, when given, is used for everything it sets (TLS, access control, routers, mode,
endpoints): only `extra` is applied over it. What it leaves unset is not zenoh's default where
that default exposes the process: an unset listen list becomes `listen` (none by default, where
zenoh would listen on every interface) and unset multicast scouting becomes
`multicast_scouting` (off, where zenoh would scout). The daemon logs what it listens on and
whether it scouts, and warns when it listens beyond loopback (`log_network`).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from qnav.contracts.errors import ConfigError

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
    """A zenoh JSON5 configuration file (TLS, access control...; `qnav certs` writes them) used
    for all it sets; listening and multicast scouting it leaves unset come from the settings
    above, not zenoh's defaults."""
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
        replaced = secure_unset_defaults(config, settings)
        if replaced:
            import logging

            logging.getLogger(__name__).info(
                "zenoh: %s leaves unset what would expose it; using %s",
                settings.config_file,
                ", ".join(replaced),
            )
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


def secure_unset_defaults(config: Any, settings: ZenohSettings) -> list[str]:
    """Replace the exposing zenoh defaults a user configuration left unset (listening on every
    interface, multicast scouting) by our settings' values; returns what was replaced."""
    import zenoh

    default = zenoh.Config()
    replaced = []
    for path, ours in (
        ("listen/endpoints", list(settings.listen)),
        ("scouting/multicast/enabled", settings.multicast_scouting),
    ):
        if config.get_json(path) == default.get_json(path):
            config.insert_json5(path, json.dumps(ours))
            replaced.append(f"{path} = {json.dumps(ours)}")
    return replaced


def network_view(config: Any) -> tuple[list[str], bool]:
    """(listen endpoints for the configured mode, multicast scouting on) of a zenoh config."""
    mode = json.loads(config.get_json("mode")) or "peer"
    listen = json.loads(config.get_json("listen/endpoints"))
    if isinstance(listen, dict):
        listen = listen.get(mode, [])
    multicast = json.loads(config.get_json("scouting/multicast/enabled"))
    return [str(endpoint) for endpoint in listen], multicast is None or bool(multicast)


LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe")
"""Endpoint protocols that never leave the machine."""


def is_loopback(endpoint: str) -> bool:
    """Whether a zenoh endpoint (PROTOCOL/HOST:PORT, maybe with ?config or #metadata) is
    reachable only from this machine. The whole host is compared, so `localhost.example.com`
    or `127.0.0.1.example.com` are not taken for loopback."""
    protocol, _, address = endpoint.partition("/")
    if protocol in LOCAL_PROTOCOLS:
        return True
    host = address.split("?")[0].split("#")[0].rsplit(":", 1)[0].strip("[]").lower()
    if host in {"localhost", "::1"}:
        return True
    parts = host.split(".")
    return len(parts) == 4 and parts[0] == "127" and all(p.isdigit() for p in parts)


def exposed_endpoints(listen: list[str]) -> list[str]:
    """The endpoints that listen beyond this machine."""
    return [endpoint for endpoint in listen if not is_loopback(endpoint)]


def log_network(config: Any) -> None:
    """Log what a session listens on and whether it scouts; warn when it is exposed."""
    import logging

    logger = logging.getLogger(__name__)
    listen, multicast = network_view(config)
    logger.info(
        "zenoh: listening on %s, multicast scouting %s",
        ", ".join(listen) or "nothing",
        "on" if multicast else "off",
    )
    exposed = exposed_endpoints(listen)
    if exposed:
        logger.warning(
            "zenoh: listening beyond loopback on %s: any host that reaches it can join",
            ", ".join(exposed),
        )
    if multicast:
        logger.warning("zenoh: multicast scouting is on: peers on the network will find this one")


class StoppedError(Exception):
    """A stop was asked for before the zenoh session opened."""


def open_session(settings: ZenohSettings, stop: threading.Event | None = None) -> Any:
    """An open zenoh session (close it, or use it in a `with` block).

    A client waits inside zenoh until something listens at its endpoint, where no Python signal
    handler runs. With `stop` the wait happens in a helper thread instead and this one watches
    `stop`: once it is set, `StoppedError` is raised at once (the helper is left to the
    interpreter's exit), so a daemon stops on SIGTERM before it ever connects."""
    import logging

    import zenoh

    if settings.session_mode == "client" and not settings.config_file:
        logging.getLogger(__name__).info(
            "zenoh: connecting to %s (waiting until something listens there)",
            ", ".join(settings.connect),
        )
    config = zenoh_config(settings)
    if settings.config_file:
        log_network(config)
    if stop is None:
        return _opened(lambda: zenoh.open(config), settings)
    outcome: dict[str, Any] = {}
    lock = threading.Lock()
    opened = threading.Event()

    def opening() -> None:
        try:
            session = _opened(lambda: zenoh.open(config), settings)
        except BaseException as error:
            outcome["error"] = error
            opened.set()
            return
        with lock:
            if outcome.get("abandoned"):
                session.close()  # opened too late: nobody will use it
                return
            outcome["session"] = session
        opened.set()

    threading.Thread(target=opening, name="zenoh-open", daemon=True).start()
    while not opened.wait(0.05):
        if stop.is_set():
            with lock:
                if "session" not in outcome and "error" not in outcome:
                    outcome["abandoned"] = True
                    raise StoppedError("stopped before the zenoh session opened")
    if "error" in outcome:
        raise outcome["error"]
    return outcome["session"]


def _opened(open_: Callable[[], Any], settings: ZenohSettings) -> Any:
    try:
        return open_()
    except Exception as error:
        raise ConfigError(
            f"cannot open a zenoh session (listen {list(settings.listen)}, "
            f"connect {list(settings.connect)}): {error}"
        ) from None


_SUBSCRIBE_MESSAGES = (
    "declare_subscriber",
    "declare_liveliness_subscriber",
    "liveliness_token",
    "liveliness_query",
    "declare_queryable",
    "query",
    "reply",
)
"""What every known identity may do on any key: subscribe, and the declarations around it."""


def secure_hub_config(
    cert_dir: str, listen: str, publishers: dict[str, tuple[str, ...]]
) -> dict[str, Any]:
    """The zenoh configuration of the hub every daemon connects to, with mutual TLS (a peer
    needs a certificate from the CA in `cert_dir`) and access control: each identity (the
    certificate's common name) may publish only its keys in `publishers` (ROS names, any
    namespace); every identity may subscribe to everything; anything else is denied."""
    identities = sorted(publishers)
    rules: list[dict[str, Any]] = [
        {
            "id": "subscribe",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": list(_SUBSCRIBE_MESSAGES),
            "key_exprs": ["**"],
        },
        {
            "id": "receive",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put", "delete"],
            "key_exprs": ["**"],
        },
    ]
    policies: list[dict[str, Any]] = [{"rules": ["subscribe", "receive"], "subjects": identities}]
    for identity in identities:
        keys = [form for name in publishers[identity] for form in (name, f"*/{name}")]
        if not keys:
            continue
        rules.append(
            {
                "id": f"publish-{identity}",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put"],
                "key_exprs": keys,
            }
        )
        policies.append({"rules": [f"publish-{identity}"], "subjects": [identity]})
    return {
        "mode": "peer",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "tls": {
                    "root_ca_certificate": f"{cert_dir}/ca.pem",
                    "listen_certificate": f"{cert_dir}/hub.pem",
                    "listen_private_key": f"{cert_dir}/hub-key.pem",
                    "enable_mtls": True,
                }
            }
        },
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": rules,
            "subjects": [{"id": i, "cert_common_names": [i]} for i in identities],
            "policies": policies,
        },
    }


def secure_client_config(cert_dir: str, identity: str, connect: str) -> dict[str, Any]:
    """The zenoh configuration of a daemon (`identity`) that connects to the secure hub."""
    return {
        "mode": "client",
        "connect": {"endpoints": [connect], "timeout_ms": -1},
        "listen": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "tls": {
                    "root_ca_certificate": f"{cert_dir}/ca.pem",
                    "connect_certificate": f"{cert_dir}/{identity}.pem",
                    "connect_private_key": f"{cert_dir}/{identity}-key.pem",
                    "enable_mtls": True,
                }
            }
        },
    }
