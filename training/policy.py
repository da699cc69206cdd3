"""A trained Q-network: the network a run's settings make, with its weights from the run folder.

Loading one imports no training loop (`tests/training/test_imports.py`).
"""

from __future__ import annotations

from pathlib import Path

import torch

from qnav.contracts.errors import ConfigError
from qnav.sim.config import WorldConfig
from qnav.training.config import TrainSettings
from qnav.training.networks import QNetwork
from qnav.training.run_folder import RunSettings, read_settings


def make_network(world: WorldConfig, settings: TrainSettings) -> QNetwork:
    """The Q-network for this world and these settings (fresh weights)."""
    beams = world.lidar.num_beams if world.lidar else None
    return QNetwork(settings.model, beams, settings.hidden_size)


def load_network(run_dir: Path) -> tuple[QNetwork, RunSettings]:
    """The run's final network (model.pt), or its latest checkpoint if it has not finished."""
    settings = read_settings(run_dir)
    network = make_network(settings.world, settings.train)
    for name, key in (("model.pt", "online"), ("checkpoint.pt", "online")):
        path = run_dir / name
        if path.exists():
            saved = torch.load(path, weights_only=False, map_location="cpu")
            network.load_state_dict(saved[key])
            network.eval()
            return network, settings
    raise ConfigError(f"{run_dir} has neither model.pt nor checkpoint.pt: nothing to load")
