"""Every `qnav ...` command in README.md's and docs/*.md's shell blocks (```sh, ```bash) parses
with the real parser: its verb exists and so does each of its options (and a value argparse
types, an int or a choice, is of its kind). docs/log/ keeps commands as they were run and is
not checked."""

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from qnav.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
SHELL_BLOCK = re.compile(r"^```(?:sh|bash|console|shell)[ \t]*\n(.*?)^```", re.M | re.S)
OPERATORS = frozenset({"&&", "||", ";", "&", "|", "(", ")"})
REDIRECTIONS = frozenset({">", ">>", "<", "2>", "&>"})
WRAPPERS = frozenset({"sudo", "exec", "time", "env"})


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _tokens(line: str) -> list[str]:
    """A shell line's words and operators, comments dropped (quotes as the shell reads them)."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    lexer.commenters = "#"
    return list(lexer)


def _segments(tokens: list[str]) -> list[list[str]]:
    """The simple commands of a line: split at its operators, redirections and their targets
    dropped."""
    segments: list[list[str]] = [[]]
    skip = False
    for token in tokens:
        if skip:
            skip = False
        elif token in REDIRECTIONS:
            skip = True
        elif token in OPERATORS:
            segments.append([])
        else:
            segments[-1].append(token)
    return [segment for segment in segments if segment]


def _qnav_argv(words: list[str]) -> list[list[str]]:
    """The qnav arguments a simple command runs: `qnav ...`, `.venv/bin/qnav ...`,
    `python -m qnav ...`, after any `NAME=value`, `sudo` or `nice -n N`, and inside `sh -c '...'`
    wherever it stands."""
    while words and (re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", words[0]) or words[0] in WRAPPERS):
        words = words[1:]
    if words[:2] == ["nice", "-n"]:
        words = words[3:]
    if not words:
        return []
    for i, word in enumerate(words[:-2]):
        if word.split("/")[-1] in {"sh", "bash"} and words[i + 1] == "-c":
            return commands_in(words[i + 2])  # also behind unshare, ssh HOST, ...
    if words[0].split("/")[-1] == "qnav":
        return [words[1:]]
    if words[0].split("/")[-1].startswith("python") and words[1:3] == ["-m", "qnav"]:
        return [words[3:]]
    return []


def commands_in(text: str) -> list[list[str]]:
    """Every qnav command of a shell text, each as its argument list (lines ending in a
    backslash joined)."""
    joined = re.sub(r"\\\n", " ", text)
    return [
        argv
        for line in joined.splitlines()
        for segment in _segments(_tokens(line))
        for argv in _qnav_argv(segment)
    ]


def documented_commands() -> list[tuple[str, list[str]]]:
    """(page, arguments) of each qnav command in the pages' shell blocks."""
    return [
        (str(page.relative_to(ROOT)), argv)
        for page in _pages()
        for block in SHELL_BLOCK.findall(page.read_text())
        for argv in commands_in(block)
    ]


def parse_error(argv: list[str]) -> str | None:
    """What the real parser says against `argv`, or None where it parses (help included)."""
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(argv)
    except SystemExit as stop:
        if stop.code not in (0, None):
            return errors.getvalue().strip().splitlines()[-1]
    return None


def test_the_pages_show_commands_of_every_group() -> None:
    verbs = {argv[0] for _, argv in documented_commands() if argv}
    assert {"train", "eval", "export", "stack", "controller", "bridge", "record"} <= verbs


@pytest.mark.parametrize(
    ("page", "argv"),
    documented_commands(),
    ids=lambda value: " ".join(value) if isinstance(value, list) else value,
)
def test_every_documented_command_parses(page: str, argv: list[str]) -> None:
    error = parse_error(argv)
    assert error is None, f"{page}: qnav {shlex.join(argv)}: {error}"


def test_the_reader_finds_commands_where_a_shell_runs_them_and_the_parser_refuses_bad_ones() -> (
    None
):
    text = (
        "qnav eval --policy RUN   # a comment --no-such\n"
        "OMP_NUM_THREADS=1 .venv/bin/qnav bench sim \\\n  --json > out.json && echo done\n"
        "unshare --net sh -c 'cd /tmp && qnav bridge --config x.toml' &\n"
        "python -m qnav scenarios | head\n"
        "echo qnav train\n"
    )
    assert commands_in(text) == [
        ["eval", "--policy", "RUN"],
        ["bench", "sim", "--json"],
        ["bridge", "--config", "x.toml"],
        ["scenarios"],
    ]
    assert parse_error(["eval", "--policy", "RUN"]) is None
    assert parse_error(["eval", "--help"]) is None
    assert "invalid choice" in (parse_error(["no-such-verb"]) or "")
    assert "unrecognized arguments" in (parse_error(["eval", "--no-such-option"]) or "")
    assert "invalid int value" in (parse_error(["reproduce", "--jobs", "N"]) or "")
