"""Rules of the package layout: contracts import nothing of ours; the car's side has no torch."""

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
    for package in [*PARTS, "qnav", "tests"]:
        bare = {name for name in _modules(package) if name.split(".")[0] in PARTS}
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
