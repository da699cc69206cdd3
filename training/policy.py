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


def load_network(run_dir: Path, weights: Path | None = None) -> tuple[QNetwork, RunSettings]:
    """The run's network from `weights` (a file of the run's); by default its final network
    (model.pt), or its latest checkpoint if it has not finished."""
    settings = read_settings(run_dir)
    network = make_network(settings.world, settings.train)
    candidates = [weights] if weights else [run_dir / "model.pt", run_dir / "checkpoint.pt"]
    for path in candidates:
        if path.exists():
            saved = torch.load(path, weights_only=False, map_location="cpu")
            network.load_state_dict(saved["online"])
            network.eval()
            return network, settings
    if weights:
        raise ConfigError(f"{weights} does not exist: nothing to load")
    raise ConfigError(f"{run_dir} has neither model.pt nor checkpoint.pt: nothing to load")
