"""Zenoh session settings shared by every daemon (controller, bridge, sim-car, recorder).

Defaults keep a session on this machine: listen on a loopback endpoint or connect to one, with
multicast scouting off, so nothing is exposed or discovered by accident. A zenoh configuration
file, when given, is used as is (TLS, access control, routers): mode, endpoints and scouting
then come from it, and only `extra` is applied over it.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
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
    """A zenoh JSON5 configuration file used as is (mode, endpoints, scouting come from it)."""
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
        config = zenoh.Config.from_file(settings.config_file)
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
