"""Rules of the package layout: contracts import nothing of ours; the car's side has no torch; the
product never imports the lab (only the CLI shell does, inside its handlers)."""

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PARTS = ["contracts", "sim", "simcar", "training", "controller", "firmware_bridge"]
OURS = (set(PARTS) - {"contracts"}) | {"qnav"}
"""What contracts may not import: every other part of ours."""
ONBOARD = ["contracts", "controller", "firmware_bridge"]


def _part(module: str) -> str:
    """The folder an absolute import names: `qnav.sim.world` -> `sim`, `numpy` -> `numpy`."""
    head, _, rest = module.partition(".")
    return rest.split(".")[0] if head == "qnav" and rest.split(".")[0] in PARTS else head


def _modules(package: str) -> set[str]:
    names: set[str] = set()
    for path in (ROOT / package).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names.add(node.module)
    return names


def _imports(package: str) -> set[str]:
    return {_part(name) for name in _modules(package)}


def test_our_folders_are_imported_only_under_the_qnav_namespace() -> None:
    # Installed, they are qnav.sim, qnav.controller, ...: a bare `sim` would not even exist.
    for package in [*PARTS, "lab", "qnav", "tests"]:
        bare = {name for name in _modules(package) if name.split(".")[0] in [*PARTS, "lab"]}
        assert not bare, f"{package}/ imports {sorted(bare)}: write qnav.{sorted(bare)[0]}"


def test_contracts_import_none_of_the_other_packages() -> None:
    assert not (_imports("contracts") & OURS)


def test_the_simulator_is_numpy_alone_and_its_processes_live_in_simcar() -> None:
    # sim/ is the pure world; the sim-in-the-loop processes (sockets, threads) are simcar/'s.
    assert not (_imports("sim") & (OURS - {"sim"}))
    assert not (_imports("sim") & {"zenoh", "pymavlink", "socket", "threading"})
    assert _imports("simcar") & OURS <= {"sim", "simcar"}


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


def _names_lab(module: str) -> bool:
    parts = module.split(".")
    return parts[:2] == ["qnav", "lab"] or parts[0] == "lab"


def _is_lab(node: ast.AST) -> bool:
    """`node` imports the lab: `import qnav.lab.x`, `from qnav.lab.x import y`, `from qnav import
    lab` (or a bare `lab`, which the namespace rule above refuses anyway)."""
    if isinstance(node, ast.Import):
        return any(_names_lab(alias.name) for alias in node.names)
    if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
        if node.module == "qnav":
            return any(alias.name == "lab" for alias in node.names)
        return _names_lab(node.module)
    return False


def _eager_lab_imports(path: Path) -> list[int]:
    """Lines of `path` that import the lab when the module is imported: outside every function
    and outside `if TYPE_CHECKING:` (which only the type checker reads)."""
    lines: list[int] = []

    def visit(node: ast.AST, lazy: bool) -> None:
        if _is_lab(node) and not lazy:
            lines.append(getattr(node, "lineno", 0))
        for child in ast.iter_child_nodes(node):
            inside = lazy or isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
            typing_only = (
                isinstance(node, ast.If)
                and isinstance(node.test, ast.Name)
                and node.test.id == "TYPE_CHECKING"
                and child in node.body
            )
            visit(child, inside or typing_only)

    visit(ast.parse(path.read_text()), lazy=False)
    return lines


def test_no_product_folder_imports_the_lab() -> None:
    # The lab (oracle, gauge, probes, imitation) studies the product; the product runs without it.
    for package in PARTS:
        found = [
            f"{path.relative_to(ROOT)}:{node.lineno}"
            for path in sorted((ROOT / package).rglob("*.py"))
            for node in ast.walk(ast.parse(path.read_text()))
            if _is_lab(node) and isinstance(node, ast.Import | ast.ImportFrom)
        ]
        assert not found, f"{package}/ imports the lab: {found}"


def test_the_cli_shell_imports_the_lab_only_inside_its_handlers() -> None:
    # qnav/'s own modules (the symlinked folders are checked above) import it lazily, so that
    # importing the product, or running a product verb, never loads the lab.
    modules = sorted(path for path in (ROOT / "qnav").glob("*.py") if not path.is_symlink())
    assert modules
    eager = {path.name: lines for path in modules if (lines := _eager_lab_imports(path))}
    assert not eager, f"module-level imports of the lab: {eager}"


def test_the_rule_sees_an_eager_import_and_forgives_a_lazy_one(tmp_path: Path) -> None:
    path = tmp_path / "shell.py"
    path.write_text(
        "from typing import TYPE_CHECKING\n"
        "from qnav.lab.oracle import run_oracle\n"
        "if TYPE_CHECKING:\n    from qnav.lab.gauge import DecisiveGauge\n"
        "def verb() -> None:\n    from qnav.lab import tracking\n"
        "from qnav import lab\n"
    )
    assert _eager_lab_imports(path) == [2, 7]


def test_only_the_shell_parses_command_lines() -> None:
    # The packages take typed settings; options and their handlers live in qnav/ (qnav.verbs).
    for package in [*PARTS, "lab"]:
        assert "argparse" not in _modules(package), package
