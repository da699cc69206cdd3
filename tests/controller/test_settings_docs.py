"""docs/controller-settings.md is the table the settings classes give."""

from pathlib import Path

from qnav.contracts.settings import to_markdown
from qnav.controller.config import DaemonConfig

ROOT = Path(__file__).resolve().parents[2]


def test_the_settings_table_in_the_docs_is_current() -> None:
    table = to_markdown(DaemonConfig())
    assert table in (ROOT / "docs" / "controller-settings.md").read_text(), (
        "paste `to_markdown(DaemonConfig())` into docs/controller-settings.md"
    )
