"""Rules of the package layout, as one table: which of our packages (and torch) each folder may
import, checked over every module by a scan of its imports, top-level and inside functions. The
car's side has no torch at run time either; the product never imports the lab (only the CLI
shell does, inside its handlers)."""

import ast
import pkgutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PARTS = ["contracts", "sim", "simcar", "training", "controller", "firmware_bridge"]
"""The product's folders (installed as qnav.<part>)."""
FOLDERS = [*PARTS, "lab", "qnav"]
"""Every folder the table covers: the product, the lab and the `qnav` shell's own modules."""
ONBOARD = ["contracts", "controller", "firmware_bridge"]

MAY_IMPORT: dict[str, frozenset[str]] = {
    "contracts": frozenset(),
    "sim": frozenset({"contracts"}),
    "simcar": frozenset({"contracts", "sim"}),
    "training": frozenset({"contracts", "sim", "torch"}),
    "controller": frozenset({"contracts"}),
    "firmware_bridge": frozenset({"contracts"}),
    "lab": frozenset({"contracts", "sim", "controller", "training", "qnav", "torch"}),
    "qnav": frozenset({*PARTS, "lab"}),
}
"""Folder -> what its modules may import: our folders by name, `qnav` for the shell's own
modules (qnav.cli, qnav.tracking, ...), and `torch`. The folder itself is always allowed."""

FILE_MAY_ALSO_IMPORT: dict[str, frozenset[str]] = {
    # Export runs the written file through the onboard runtime before it ships it.
    "training/export.py": frozenset({"controller"}),
}
"""File-level exceptions: a file -> what it may import beyond its folder's row."""

ONLY_LAZILY: dict[str, frozenset[str]] = {
    # Importing the product, or running a product verb, never loads the lab.
    "qnav": frozenset({"lab"}),
}
"""Folder -> what it may import only inside a function (or under `if TYPE_CHECKING:`)."""


@dataclass(frozen=True)
class Import:
    """One import statement's name, as the scan sees it."""

    path: str
    """The importing file, relative to the repository root."""
    line: int
    """Its line number."""
    name: str
    """The module named: `qnav.sim.world`, `torch.nn`, `qnav.lab` for `from qnav import lab`."""
    lazy: bool
    """Inside a function or lambda, or under `if TYPE_CHECKING:`: not run on the module's import."""

    def __str__(self) -> str:
        return f"{self.path}:{self.line} imports {self.name}{' (lazily)' if self.lazy else ''}"


def _target(name: str) -> str | None:
    """What the table calls an imported module: `qnav.sim.world` -> `sim`, `qnav.cli` -> `qnav`,
    `torch.nn` -> `torch`, `numpy` -> None (outside the table)."""
    head, _, rest = name.partition(".")
    if head == "torch":
        return "torch"
    if head != "qnav":
        return None
    part = rest.split(".")[0]
    return part if part in FOLDERS else "qnav"


def _folder_files(folder: str) -> list[Path]:
    """The modules of a folder (for `qnav`, the shell's own)."""
    return sorted((ROOT / folder).rglob("*.py"))


def _imports_of(path: Path, relative_to: Path = ROOT) -> list[Import]:
    """Every import in `path`, at any depth, with whether it runs only when called."""
    found: list[Import] = []
    where = str(path.relative_to(relative_to))

    def visit(node: ast.AST, lazy: bool) -> None:
        if isinstance(node, ast.Import):
            found.extend(Import(where, node.lineno, alias.name, lazy) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            module = "." * node.level + (node.module or "")
            if module == "qnav":  # `from qnav import lab`: the package named is qnav.lab
                found.extend(Import(where, node.lineno, f"qnav.{a.name}", lazy) for a in node.names)
            else:
                found.append(Import(where, node.lineno, module, lazy))
        for child in ast.iter_child_nodes(node):
            inside = isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
            typing_only = (
                isinstance(node, ast.If)
                and isinstance(node.test, ast.Name)
                and node.test.id == "TYPE_CHECKING"
                and child in node.body
            )
            visit(child, lazy or inside or typing_only)

    visit(ast.parse(path.read_text()), lazy=False)
    return found


def _breaches(folder: str, imports: list[Import]) -> list[Import]:
    """The imports of `folder`'s modules that its row of the table (with the file-level
    exceptions and the lazy-only rule) does not allow."""
    wrong: list[Import] = []
    for found in imports:
        target = _target(found.name)
        if target is None or target == folder:
            continue
        allowed = MAY_IMPORT[folder] | FILE_MAY_ALSO_IMPORT.get(found.path, frozenset())
        if target not in allowed or (target in ONLY_LAZILY.get(folder, ()) and not found.lazy):
            wrong.append(found)
    return wrong


def test_the_table_covers_every_folder_and_names_only_folders() -> None:
    assert set(MAY_IMPORT) == set(FOLDERS)
    for allowed in [*MAY_IMPORT.values(), *FILE_MAY_ALSO_IMPORT.values(), *ONLY_LAZILY.values()]:
        assert allowed <= {*FOLDERS, "torch"}, sorted(allowed)
    for path in FILE_MAY_ALSO_IMPORT:
        assert (ROOT / path).is_file(), f"{path} is in FILE_MAY_ALSO_IMPORT but does not exist"


def test_each_folder_installs_as_its_package_under_qnav_and_no_link_stands_in() -> None:
    # pyproject's package-dir maps sim/ to qnav.sim and so on: no symlink in the checkout, and
    # the import scan reads the folders the wheel is built from.
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    expected = {"qnav" if f == "qnav" else f"qnav.{f}": f for f in FOLDERS}
    assert setuptools["package-dir"] == expected
    assert set(setuptools["packages"]) == {*expected, "qnav.verbs"}
    linked = [str(p) for f in FOLDERS for p in [ROOT / f, *(ROOT / f).rglob("*")] if p.is_symlink()]
    assert not linked


def test_every_module_imports_only_what_its_folders_row_allows() -> None:
    # contracts: none of ours; sim, controller, firmware_bridge: contracts; simcar: contracts and
    # sim; training: contracts, sim (and controller in export.py only); torch only in training/
    # and lab/; no product folder imports the lab; the shell imports it only inside functions.
    found = {
        breach
        for folder in FOLDERS
        for path in _folder_files(folder)
        for breach in _breaches(folder, _imports_of(path))
    }
    assert not found, "imports the layering table forbids:\n" + "\n".join(sorted(map(str, found)))


def test_every_import_of_ours_is_absolute_so_the_scan_sees_it() -> None:
    relative = [
        str(found)
        for folder in FOLDERS
        for path in _folder_files(folder)
        for found in _imports_of(path)
        if found.name.startswith(".")
    ]
    assert not relative, f"write the qnav.X name: {relative}"


def test_our_folders_are_imported_only_under_the_qnav_namespace() -> None:
    # Installed, they are qnav.sim, qnav.controller, ...: a bare `sim` would not even exist.
    for folder in [*FOLDERS, "tests"]:
        files = _folder_files(folder) if folder != "tests" else (ROOT / "tests").rglob("*.py")
        bare = [
            str(found)
            for path in files
            for found in _imports_of(path)
            if found.name.split(".")[0] in [*PARTS, "lab"]
        ]
        assert not bare, f"{folder}/: {bare}: write qnav.<folder>"


def test_the_simulator_opens_no_sockets_and_starts_no_threads() -> None:
    # sim/ is the pure world; the sim-in-the-loop processes (sockets, threads) are simcar/'s.
    heads = {
        found.name.split(".")[0] for path in _folder_files("sim") for found in _imports_of(path)
    }
    assert not (heads & {"zenoh", "pymavlink", "socket", "threading"})


def test_onboard_packages_never_import_torch() -> None:
    modules = []
    for package in ONBOARD:
        modules.append(f"qnav.{package}")
        modules += [
            f"qnav.{package}.{info.name}" for info in pkgutil.iter_modules([str(ROOT / package)])
        ]
    code = (
        "import importlib, sys\n"
        f"for name in {modules!r}: importlib.import_module(name)\n"
        "print('torch' in sys.modules, 'ray' in sys.modules)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True
    )
    assert result.stdout.strip() == "False False"  # nor Ray (the desktop's [cluster] extra)


def test_the_scan_sees_each_kind_of_import_and_the_table_names_each_breach(tmp_path: Path) -> None:
    (tmp_path / "shell.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "from qnav.lab.oracle import run_oracle\n"
        "if TYPE_CHECKING:\n    from qnav.lab.diagnose import Diagnosis\n"
        "def verb() -> None:\n    from qnav.lab import tracking\n"
        "from qnav import lab, sim\n"
        "import torch.nn, numpy\n"
        "class A:\n    def f(self) -> None:\n        import qnav.controller.policy\n"
    )
    found = _imports_of(tmp_path / "shell.py", relative_to=tmp_path)
    assert [(f.line, f.name, f.lazy) for f in found] == [
        (1, "typing", False),
        (2, "qnav.lab.oracle", False),
        (4, "qnav.lab.diagnose", True),
        (6, "qnav.lab", True),
        (7, "qnav.lab", False),
        (7, "qnav.sim", False),
        (8, "torch.nn", False),
        (8, "numpy", False),
        (11, "qnav.controller.policy", True),
    ]
    # In the shell: the eager lab imports and torch break the table; the lazy ones do not.
    assert [str(b) for b in _breaches("qnav", found)] == [
        "shell.py:2 imports qnav.lab.oracle",
        "shell.py:7 imports qnav.lab",
        "shell.py:8 imports torch.nn",
    ]
    # In the controller every import of another folder of ours breaks it, lazy or not.
    assert [b.line for b in _breaches("controller", found)] == [2, 4, 6, 7, 7, 8]


def test_only_the_shell_parses_command_lines() -> None:
    # The packages take typed settings; options and their handlers live in qnav/ (qnav.verbs).
    parsers = [
        str(found)
        for folder in [*PARTS, "lab"]
        for path in _folder_files(folder)
        for found in _imports_of(path)
        if found.name == "argparse"
    ]
    assert parsers == []


MAX_FUNCTION_LINES = 80
"""The longest a function of the product may be, from its def line to its last (decorators
aside); the lab and the tests are not the product."""


def _long_functions(path: Path, relative_to: Path = ROOT) -> list[str]:
    """The functions and methods of `path`, at any depth, longer than `MAX_FUNCTION_LINES`."""
    where = path.relative_to(relative_to)
    return [
        f"{where}:{node.lineno} {node.name} ({length} lines)"
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and (length := (node.end_lineno or node.lineno) - node.lineno + 1) > MAX_FUNCTION_LINES
    ]


def test_no_function_of_the_product_is_longer_than_80_lines() -> None:
    long = [found for folder in [*PARTS, "qnav"] for path in _folder_files(folder)
            for found in _long_functions(path)]  # fmt: skip
    assert not long, "split these:\n" + "\n".join(long)


def test_the_length_check_sees_methods_and_nested_functions(tmp_path: Path) -> None:
    def function(name: str, lines: int, indent: str = "") -> str:
        return f"{indent}def {name}() -> None:\n" + f"{indent}    x = 1\n" * (lines - 1)

    (tmp_path / "long.py").write_text(
        function("short", 80)
        + "class A:\n"
        + function("method", 81, "    ")
        + "def outer() -> None:\n"
        + function("inner", 81, "    ")
    )
    found = _long_functions(tmp_path / "long.py", relative_to=tmp_path)
    assert sorted(entry.split()[1] for entry in found) == ["inner", "method", "outer"]
