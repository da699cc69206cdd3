"""Zenoh session settings: a user's config file stays local unless it says otherwise, and the log
says what it exposes; the docs' settings tables show the zenoh settings as they are."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import to_markdown
from qnav.contracts.transport import (
    ZenohSettings,
    exposed_endpoints,
    is_loopback,
    log_network,
    network_view,
    zenoh_config,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/127.0.0.1:7447",
        "tls/localhost:7447",
        "tcp/[::1]:7447",
        "udp/127.0.0.2:7447#iface=lo",
        "unixsock-stream//tmp/zenoh.sock",
    ],
)
def test_loopback_endpoints(endpoint: str) -> None:
    assert is_loopback(endpoint)


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/[::]:7447",
        "tcp/0.0.0.0:7447",
        "tls/192.168.1.5:7447",
        "tcp/car.local:7447",
        "tcp/localhost.example.com:7447",
        "tcp/127.0.0.1.example.com:7447",
    ],
)
def test_endpoints_beyond_loopback(endpoint: str) -> None:
    assert not is_loopback(endpoint)
    assert exposed_endpoints([endpoint, "tcp/127.0.0.1:7447"]) == [endpoint]


def _settings(tmp_path: Path, text: str) -> ZenohSettings:
    path = tmp_path / "zenoh.json5"
    path.write_text(text)
    return ZenohSettings(config_file=str(path))


@pytest.mark.parametrize("mode", ["peer", "router"])
def test_a_minimal_user_file_listens_nowhere_without_multicast_and_says_so(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, mode: str
) -> None:
    caplog.set_level("INFO", logger="qnav.contracts.transport")
    config = zenoh_config(_settings(tmp_path, f'{{ mode: "{mode}" }}'))
    assert network_view(config) == ([], False)
    assert "leaves unset what would expose it" in caplog.text
    assert "listen/endpoints = []" in caplog.text
    assert "scouting/multicast/enabled = false" in caplog.text
    caplog.clear()
    log_network(config)
    assert "listening on nothing, multicast scouting off" in caplog.text
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_what_the_file_sets_is_kept_and_exposure_is_warned(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("INFO", logger="qnav.contracts.transport")
    text = (
        '{ mode: "peer", listen: { endpoints: ["tcp/0.0.0.0:7447", "tcp/127.0.0.1:7448"] },'
        " scouting: { multicast: { enabled: true } } }"
    )
    config = zenoh_config(_settings(tmp_path, text))
    assert network_view(config) == (["tcp/0.0.0.0:7447", "tcp/127.0.0.1:7448"], True)
    assert "leaves unset" not in caplog.text
    log_network(config)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("beyond loopback on tcp/0.0.0.0:7447:" in w for w in warnings), warnings
    assert not any("7448" in w for w in warnings)
    assert any("multicast scouting is on" in w for w in warnings)


def test_an_explicit_loopback_listen_is_kept(tmp_path: Path) -> None:
    text = '{ mode: "router", listen: { endpoints: ["tcp/127.0.0.1:7449"] } }'
    config = zenoh_config(_settings(tmp_path, text))
    assert network_view(config) == (["tcp/127.0.0.1:7449"], False)


def test_a_malformed_or_missing_file_names_the_setting(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"zenoh\.config_file"):
        zenoh_config(_settings(tmp_path, "{ mode: "))
    with pytest.raises(ConfigError, match=r"zenoh\.config_file"):
        zenoh_config(_settings(tmp_path, '{ mode: "peer", no_such_setting: 1 }'))
    with pytest.raises(ConfigError, match=r"zenoh\.config_file"):
        ZenohSettings(config_file=str(tmp_path / "missing.json5"))


def _zenoh_rows(table: str) -> list[str]:
    """The section's rows as a daemon's table shows them (names prefixed with `zenoh.`)."""
    rows = re.findall(r"^\| `[a-z_]+` \|.*$", table, re.M)
    return [row.replace("| `", "| `zenoh.", 1) for row in rows]


@pytest.mark.parametrize("doc", ["controller-settings.md", "bridge.md"])
def test_the_docs_show_the_zenoh_settings_as_they_are(doc: str) -> None:
    rows = _zenoh_rows(to_markdown(ZenohSettings()))
    assert rows and any('`"auto"`' in row for row in rows)
    text = (ROOT / "docs" / doc).read_text()
    for row in rows:
        assert row in text, f"docs/{doc} is stale; paste to_markdown's row: {row}"
