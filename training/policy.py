"""Loading a trained Q-network from a run folder."""

from __future__ import annotations

from pathlib import Path

import torch

from contracts.errors import ConfigError
from training.networks import QNetwork
from training.run import RunSettings, make_network, read_settings


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
