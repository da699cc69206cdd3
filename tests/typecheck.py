"""mypy over qnav as it installs. pyproject maps folders to packages (its package-dir: `sim/` is
`qnav.sim`), which mypy cannot read, so this gives mypy every mapped folder's modules under their
installed names, beside what the command line names: `python -m tests.typecheck qnav tests` is
`mypy qnav tests` over the whole package (`make typecheck`). Its cache is its own: a plain
`mypy` run, which finds no `qnav.sim`, leaves cached misses this run would otherwise trust."""

import os
import sys
import time
import tomllib
from pathlib import Path

from mypy import util
from mypy.fscache import FileSystemCache
from mypy.main import process_options, run_build
from mypy.modulefinder import BuildSource

ROOT = Path(__file__).resolve().parents[1]


def mapped_folders(pyproject: Path = ROOT / "pyproject.toml") -> dict[str, Path]:
    """Package -> folder, as pyproject's [tool.setuptools.package-dir] maps them."""
    table = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["package-dir"]
    return {package: pyproject.parent / folder for package, folder in table.items()}


def installed_name(package: str, folder: Path, path: Path) -> str:
    """The module `path` (a .py file under `folder`) installs as: `sim/world.py` in `qnav.sim`
    is `qnav.sim.world`, `sim/__init__.py` is `qnav.sim`."""
    parts = path.relative_to(folder).with_suffix("").parts
    return ".".join((package, *(parts[:-1] if parts[-1] == "__init__" else parts)))


def mapped_sources(folders: dict[str, Path]) -> list[BuildSource]:
    """Every module of the mapped folders, under its installed name."""
    return [
        BuildSource(os.path.relpath(path), installed_name(package, folder, path))
        for package, folder in sorted(folders.items())
        for path in sorted(folder.rglob("*.py"))
    ]


def main(args: list[str]) -> int:
    """mypy's exit status: 0 clean, 1 errors, 2 an error that stopped the check."""
    started = time.time()
    fscache = FileSystemCache()
    sources, options = process_options(args, fscache=fscache)
    options.cache_dir = str(Path(options.cache_dir) / "package-dir")
    named = {source.module for source in sources}
    sources += [s for s in mapped_sources(mapped_folders()) if s.module not in named]
    _, messages, blockers = run_build(sources, options, fscache, started, sys.stdout, sys.stderr)
    errors, _, files = util.count_stats(messages)
    formatter = util.FancyFormatter(sys.stdout, sys.stderr, options.hide_error_codes)
    if errors:
        print(formatter.format_error(errors, files, len(sources), blockers=blockers))
        return 2 if blockers else 1
    print(formatter.format_success(len(sources)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
