"""`import qnav` registers the simulator's gymnasium ids (`qnav/<Scenario>-v0`, sim/gym_env.py):
at once where gymnasium is loaded already, else as soon as it is, so a process that never loads
gymnasium (the car's daemons) never does for them. Gymnasium 1.x reads no plugin entry points."""

import importlib.abc
import importlib.util
import sys
from collections.abc import Callable, Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType


def register() -> None:
    """Register the ids (the module registers them when it is imported)."""
    from qnav.sim import gym_env  # noqa: F401


class AfterImport(importlib.abc.MetaPathFinder):
    """Calls `then` right after the module `name` has run, the first time it is imported."""

    def __init__(self, name: str, then: Callable[[], None]) -> None:
        self.name = name
        self.then = then

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        if fullname != self.name:
            return None
        sys.meta_path.remove(self)  # the other finders find it; this one only waits once
        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None:
            return spec
        run = spec.loader.exec_module

        def run_then(module: ModuleType) -> None:
            run(module)
            self.then()

        spec.loader.exec_module = run_then  # type: ignore[method-assign]
        return spec


def register_when_gymnasium_loads() -> None:
    """Register the ids now if gymnasium is loaded, else once it is (once either way)."""
    if "gymnasium" in sys.modules:
        register()
    elif not any(isinstance(finder, AfterImport) for finder in sys.meta_path):
        sys.meta_path.insert(0, AfterImport("gymnasium", register))
