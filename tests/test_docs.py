"""The docs point at what exists: every relative link in README.md and docs/ resolves to a file,
and every path README names (its layout table's files, functions and classes above all) is there."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s]+)\)")
"""A markdown link's or image's target: `[text](target)`, `![alt](target)`."""
CODE = re.compile(r"`([^`]+)`")
PATHLIKE = re.compile(r"[\w.-]+(/[\w.-]*)+")
"""A backticked repository path: `sim/task.py`, `controller/`, `config/bridge.toml`."""
NAME = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")
"""A backticked Python name: `reward`, `Controller._stop_reason`."""


def _markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _broken_links(path: Path) -> list[str]:
    """The relative links of `path` whose file (anchors dropped) does not exist."""
    broken: list[str] = []
    for target in LINK.findall(path.read_text()):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # a web address, mailto:, or an anchor on the same page
        if not (path.parent / target.split("#")[0]).exists():
            broken.append(target)
    return broken


def _table_rows(text: str, header: str) -> list[list[str]]:
    """The cells of each row of the markdown table whose header line is `header`."""
    lines = text.splitlines()
    start = lines.index(header) + 2  # past the header and the |---| line
    rows: list[list[str]] = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in re.split(r"(?<!\\)\|", line)[1:-1]])
    return rows


def _defines(path: Path, name: str) -> bool:
    """`path` defines `name` (a function, class or module-level constant)."""
    pattern = rf"^\s*(def|class) {name}\b|^{name}\s*[:=]"
    return re.search(pattern, path.read_text(), re.M) is not None


def _missing_in_layout_row(edit: str) -> list[str]:
    """What a layout row's 'edit' cell names that is not there: each path must exist, and each
    Python name must be defined in one of the cell's .py files."""
    codes = CODE.findall(edit)
    paths = [code for code in codes if PATHLIKE.fullmatch(code)]
    files = [ROOT / p for p in paths if p.endswith(".py")]
    missing = [p for p in paths if not (ROOT / p).exists()]
    for code in codes:
        if NAME.fullmatch(code) and "." not in code.split(".")[0] and not code.endswith(".py"):
            name = code.split(".")[-1]
            if not any(f.is_file() and _defines(f, name) for f in files):
                missing.append(code)
    return missing


def test_every_relative_link_in_readme_and_docs_resolves() -> None:
    broken = {
        str(path.relative_to(ROOT)): links
        for path in _markdown_files()
        if (links := _broken_links(path))
    }
    assert not broken, f"links to nothing: {broken}"


def test_every_path_and_name_in_the_readmes_layout_table_exists() -> None:
    rows = _table_rows((ROOT / "README.md").read_text(), "| to change | edit |")
    assert len(rows) >= 14  # one per thing a newcomer changes
    missing = {what: gone for what, edit in rows if (gone := _missing_in_layout_row(edit))}
    assert not missing, f"README's layout table names what is not there: {missing}"


def test_every_path_the_readme_names_exists() -> None:
    text = re.sub(r"^```.*?^```", "", (ROOT / "README.md").read_text(), flags=re.M | re.S)
    paths = {code for code in CODE.findall(text) if PATHLIKE.fullmatch(code)}
    assert paths
    assert not sorted(p for p in paths if not (ROOT / p).exists())


def test_the_checks_see_a_broken_link_a_missing_file_and_an_undefined_name(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("[a](https://x.org) [b](#here) [c](page.md#top) [d](gone.md) ![e](img/no.png)")
    assert _broken_links(page) == ["gone.md", "img/no.png"]
    assert _missing_in_layout_row("`sim/task.py`: `reward`, `no_such_function`") == [
        "no_such_function"
    ]
    assert _missing_in_layout_row("`sim/tasks.py`: `reward`") == ["sim/tasks.py", "reward"]
    assert _missing_in_layout_row("`controller/decision.py`: `Controller._stop_reason`") == []
    rows = _table_rows("x\n| a | b |\n|---|---|\n| `p\\|q` | r |\n\ny", "| a | b |")
    assert rows == [["`p\\|q`", "r"]]


STATUS_HEADER = "| part | state and headline figure (command) | docs |"
MAX_STATUS_WORDS = 25


def test_each_cell_of_the_readmes_status_table_is_short() -> None:
    rows = _table_rows((ROOT / "README.md").read_text(), STATUS_HEADER)
    assert len(rows) >= 10
    long = {
        row[0]: n for row in rows for cell in row if (n := len(cell.split())) > MAX_STATUS_WORDS
    }
    assert not long, f"status cells over {MAX_STATUS_WORDS} words: {long}"


def test_the_readme_names_the_shipped_controller_and_its_figures() -> None:
    text = (ROOT / "README.md").read_text()
    assert '`lookahead.mode = "shield"`' in text and "`[proximity]`" in text
    shipped = (ROOT / "config" / "controller.toml").read_text()
    assert 'mode = "shield"' in shipped and "enabled = true" in shipped


MAX_PAGE_LINES = 350


def test_no_reference_page_is_longer_than_350_lines() -> None:
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]  # docs/log/ holds records
    long = {p.name: n for p in pages if (n := len(p.read_text().splitlines())) > MAX_PAGE_LINES}
    assert not long, f"pages over {MAX_PAGE_LINES} lines (dated records go to docs/log/): {long}"
