"""A training run: collect, replay with re-drawn targets, update, evaluate, checkpoint.

Everything lives in one run folder:

    settings.toml      world and learner settings (a resumed run must match them)
    episodes/          collected episodes, one file per round (no completed episode is lost)
    checkpoint.pt      networks, optimiser, counters, history (written atomically each round)
    progress.csv       one row per round: episodes, iterations, time, exploration, success
    success.png        success during training (the paper's figures 5, 6, 8, 9)
    model.pt           the final online network with its world and learner settings
    results.json       the final test under the paper's protocol

A run killed at any moment resumes from its last checkpoint when started again with the same
folder: rounds collected after that checkpoint are read back from `episodes/` and trained on.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import subprocess
import time
import tomllib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from tqdm import tqdm

from contracts.errors import ConfigError
from contracts.motion import Outcome
from contracts.observation import distance_scale_m, encode_scan
from contracts.settings import from_dict, to_dict, to_toml
from sim.config import WorldConfig
from sim.decisive import DecisiveStates, GaugeSettings, cached, score
from sim.evaluate import EvalResult, EvalSettings, evaluate
from sim.oracle import OracleDriver
from sim.world import observe, reset
from training.agent import TorchAgent, greedy_actions
from training.collect import collect_round
from training.config import TrainSettings
from training.episode_log import read_rounds, write_round
from training.learner import DemonstrationLoss, NextScanLoss, td_update
from training.networks import NextScanPredictor, QNetwork, centre_encoder
from training.replay import Episode, EpisodeReplay

REACHED_LEVELS = (0.5, 0.9, 0.99)
"""Validation success levels whose first crossing results.json records."""
VALIDATION_SEED = 999
"""Layouts of the evaluations during training (the final test uses EvalSettings' own seed)."""
_ENCODER_INIT_SEED = 4_242
"""Layouts whose first scans centre the lidar encoder at the start of a run."""
_TRAIN_LAYOUT_SEED = 1_000_003


@dataclass
class Progress:
    """Counters and history of a run, saved with every checkpoint."""

    rounds: int = 0
    episodes: int = 0
    iterations: int = 0
    collect_s: float = 0.0
    train_s: float = 0.0
    eval_s: float = 0.0
    best_success: float = -1.0
    history: list[dict[str, float]] = field(default_factory=list)


def make_network(world: WorldConfig, settings: TrainSettings) -> QNetwork:
    """The Q-network for this world and these settings."""
    beams = world.lidar.num_beams if world.lidar else None
    return QNetwork(settings.model, beams, settings.hidden_size)


def next_scan_loss(
    world: WorldConfig, settings: TrainSettings, network: QNetwork
) -> NextScanLoss | None:
    """The auxiliary next-scan loss the settings ask for, with a fresh predictor (or None)."""
    if settings.next_scan_weight == 0.0 or world.lidar is None:
        return None
    beams = world.lidar.num_beams
    if beams % settings.next_scan_sectors:
        raise ConfigError(
            f"train.next_scan_sectors = {settings.next_scan_sectors} does not divide the "
            f"lidar's {beams} beams"
        )
    return NextScanLoss(
        predictor=NextScanPredictor(network.summary_size, settings.next_scan_sectors),
        weight=settings.next_scan_weight,
        sectors=settings.next_scan_sectors,
        near_fraction=settings.next_scan_range_m / distance_scale_m(world.lidar),
    )


def policy_agent(
    network: QNetwork, world: WorldConfig, num_worlds: int, window: int, **kwargs: Any
) -> TorchAgent:
    """A greedy (or epsilon-greedy) agent of the network for this world."""
    return TorchAgent(network, num_worlds, window, distance_scale_m(world.lidar), **kwargs)


@dataclass(frozen=True)
class RunSettings:
    """What a run folder's settings.toml holds."""

    SECTION = ""

    world: WorldConfig
    """The world trained in."""
    train: TrainSettings
    """The learner."""


def read_settings(run_dir: Path) -> RunSettings:
    """The world and learner settings a run folder was started with."""
    path = run_dir / "settings.toml"
    if not path.exists():
        raise ConfigError(f"{run_dir} is not a training run: it has no settings.toml")
    return from_dict(RunSettings, tomllib.loads(path.read_text()))


def train(
    world: WorldConfig, settings: TrainSettings, run_dir: Path, progress: bool = True
) -> dict[str, Any]:
    """Run (or resume) training in `run_dir`; returns the final test results."""
    world = replace(world, max_episode_steps=settings.max_episode_steps)
    run_dir.mkdir(parents=True, exist_ok=True)
    settings_path = run_dir / "settings.toml"
    run_settings = RunSettings(world, settings)
    if settings_path.exists() and read_settings(run_dir) != run_settings:
        raise ConfigError(
            f"{run_dir} holds a run with other settings ({settings_path}); "
            "resume it with the same settings or choose another folder"
        )
    settings_path.write_text(to_toml(run_settings))
    torch.set_num_threads(settings.threads)
    torch.manual_seed(settings.seed)
    device = torch.device(
        ("cuda" if torch.cuda.is_available() else "cpu")
        if settings.device == "auto"
        else settings.device
    )
    bf16 = settings.bf16_matmul and (device.type == "cuda" or cpu_has_bf16())
    online = make_network(world, settings)
    if settings.encoder_init == "centred" and online.encoder is not None:
        centre_encoder(online.encoder, torch.from_numpy(first_scans(world, _ENCODER_INIT_SEED)))
    online = online.to(device)
    target = copy.deepcopy(online)
    next_scan = next_scan_loss(world, settings, online)
    demonstration = (
        DemonstrationLoss(settings.demonstration_margin, settings.demonstration_loss_weight)
        if settings.demonstration_episodes
        else None
    )
    trained = list(online.parameters())
    if next_scan is not None:
        next_scan.predictor.to(device)
        trained += list(next_scan.predictor.parameters())
    optimizer = torch.optim.Adam(trained, lr=settings.learning_rate)
    state = Progress()
    checkpoint = run_dir / "checkpoint.pt"
    if checkpoint.exists():
        saved = torch.load(checkpoint, weights_only=False, map_location=device)
        online.load_state_dict(saved["online"])
        target.load_state_dict(saved["target"])
        optimizer.load_state_dict(saved["optimizer"])
        if next_scan is not None:
            next_scan.predictor.load_state_dict(saved["next_scan"])
        state = Progress(**saved["progress"])
    replay = EpisodeReplay(
        world, settings.episodes * (settings.max_episode_steps + 1), settings.window
    )
    logged = read_rounds(run_dir / "episodes")
    for episodes in logged:
        for episode in episodes:
            replay.add(episode)
    logged_episodes = sum(len(r) for r in logged)
    if logged_episodes < state.episodes:
        raise ConfigError(f"{run_dir}/episodes holds fewer episodes than its checkpoint")

    decisive: DecisiveStates | None = None
    bar = tqdm(
        total=settings.episodes,
        initial=state.episodes,
        unit="ep",
        disable=not progress,
        desc=f"train {world.name} {settings.model} seed {settings.seed}",
    )
    while state.episodes < settings.episodes:
        round_index = state.rounds
        started = time.perf_counter()
        if round_index < len(logged):
            episodes = logged[round_index]
        else:
            episodes = _collect(world, settings, online, state.episodes, round_index)
            write_round(run_dir / "episodes", round_index, episodes)
            for episode in episodes:
                replay.add(episode)
        state.collect_s += time.perf_counter() - started
        state.episodes += len(episodes)
        state.rounds += 1

        started = time.perf_counter()
        owed = math.floor(
            settings.iterations_per_episode * max(0, state.episodes - settings.warmup_episodes)
        )
        sampler = np.random.default_rng([settings.seed, round_index])
        losses = []
        online.train()
        while state.iterations < owed:
            batch = replay.sample(
                settings.batch_size,
                sampler,
                settings.relabel,
                settings.n_step,
                settings.gamma,
                mirror_probability=settings.mirror_probability,
                obstacles=settings.obstacle_redraw(),
                priority_exponent=settings.priority_exponent,
                priority_correction=settings.priority_correction(state.iterations),
            )
            update = td_update(
                online,
                target,
                optimizer,
                batch,
                window=settings.window,
                loss_kind=settings.loss,
                grad_clip_norm=settings.grad_clip_norm,
                bf16=bf16,
                next_scan=next_scan,
                demonstration=demonstration,
            )
            losses.append(update.loss)
            if settings.priority_exponent > 0.0 and batch.stored is not None:
                replay.reprioritise(batch.stored, update.td_error)
            state.iterations += 1
            if settings.target_smoothing:
                soft_update(target, online, settings.target_smoothing)
            elif state.iterations % settings.target_update_period == 0:
                target.load_state_dict(online.state_dict())
        state.train_s += time.perf_counter() - started

        row: dict[str, float] = {
            "episodes": state.episodes,
            "iterations": state.iterations,
            "wall_s": round(state.collect_s + state.train_s + state.eval_s, 2),
            "epsilon": round(settings.epsilon(state.episodes - 1), 4),
            "train_success": float(np.mean([e.outcome == Outcome.SUCCESS for e in episodes])),
            "train_collision": float(np.mean([e.outcome == Outcome.COLLISION for e in episodes])),
            "loss": float(np.mean(losses)) if losses else math.nan,
        }
        if _crossed(settings.snapshot_every_episodes, state.episodes, len(episodes)):
            snapshots = run_dir / "snapshots"
            snapshots.mkdir(exist_ok=True)
            torch.save(
                {"online": online.state_dict(), "iterations": state.iterations},
                snapshots / f"episodes-{state.episodes:05d}.pt",
            )
        if _crossed(settings.eval_every_episodes, state.episodes, len(episodes)):
            started = time.perf_counter()
            result = _evaluate(
                world,
                settings=settings,
                network=online,
                episodes=settings.eval_episodes,
                seed=VALIDATION_SEED,
                max_steps=settings.max_episode_steps,
            )
            if settings.keep_best and result.success >= state.best_success:
                state.best_success = result.success
                partial = run_dir / "best.pt.partial"
                torch.save({"online": online.state_dict(), "episodes": state.episodes}, partial)
                partial.replace(run_dir / "best.pt")
            row |= {
                "eval_success": result.success,
                "eval_collision": result.collision,
                "eval_unfinished": result.unfinished,
            }
            if settings.gauge_episodes and world.obstacles.count:
                if decisive is None:
                    decisive = decisive_states(world, settings, progress)
                chosen = greedy_actions(online, decisive.windows)
                judged = score(decisive, chosen)
                row["decisive_safe"] = round(judged.safe, 4)
                row["decisive_balanced"] = round(judged.balanced, 4)
            state.eval_s += time.perf_counter() - started
        state.history.append(row)
        _checkpoint(checkpoint, online, target, optimizer, state, next_scan=next_scan)
        _write_progress(
            run_dir, state.history, f"{world.name}, {settings.model}, seed {settings.seed}"
        )
        bar.update(len(episodes))
        bar.set_postfix(
            eps=f"{row['epsilon']:.3f}",
            loss=f"{row['loss']:.4f}",
            val=f"{row.get('eval_success', math.nan):.2f}",
        )
    bar.close()

    results_path = run_dir / "results.json"
    if results_path.exists():
        return dict(json.loads(results_path.read_text()))
    shipped = online.state_dict()
    if settings.keep_best and (run_dir / "best.pt").exists():
        shipped = torch.load(run_dir / "best.pt", weights_only=False, map_location=device)["online"]
        online.load_state_dict(shipped)
    torch.save(
        {"online": shipped, "world": to_dict(world), "train": to_dict(settings)},
        run_dir / "model.pt",
    )
    started = time.perf_counter()
    test = EvalSettings()
    final = _evaluate(
        world,
        settings=settings,
        network=online,
        episodes=settings.final_eval_episodes,
        seed=test.seed,
        max_steps=test.max_episode_steps,
    )
    results = {
        "scenario": world.name,
        "model": settings.model,
        "seed": settings.seed,
        "relabel": settings.relabel,
        "test": {k: v for k, v in asdict(final).items() if k != "mean_steps"},
        "episodes": state.episodes,
        "iterations": state.iterations,
        "first_reached": {
            str(level): first_reached(state.history, level) for level in REACHED_LEVELS
        },
        "collect_s": round(state.collect_s, 1),
        "train_s": round(state.train_s, 1),
        "eval_s": round(state.eval_s + time.perf_counter() - started, 1),
        "commit": source_commit(),
    }
    results_path.write_text(json.dumps(results, indent=2) + "\n")
    return results


def source_commit() -> str:
    """The git revision of this source tree ("+dirty" if it has uncommitted changes)."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def cpu_has_bf16() -> bool:
    """Whether this CPU multiplies bfloat16 natively (otherwise autocast would be slower)."""
    checks = ("_is_amx_tile_supported", "_is_avx512_bf16_supported")
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def decisive_states(
    world: WorldConfig, settings: TrainSettings, progress: bool = False
) -> DecisiveStates:
    """The gauge's decisive states for this world, with the run's window and episode length."""
    gauge = GaugeSettings(
        episodes_per_driver=settings.gauge_episodes,
        max_episode_steps=settings.max_episode_steps,
        window=settings.window,
    )
    return cached(world, gauge, progress)


def soft_update(target: QNetwork, online: QNetwork, rate: float) -> None:
    """target <- (1 - rate) * target + rate * online, parameter by parameter."""
    with torch.no_grad():
        for mine, theirs in zip(target.parameters(), online.parameters(), strict=True):
            mine.lerp_(theirs, rate)


def first_reached(history: list[dict[str, float]], level: float) -> dict[str, float] | None:
    """Episodes, iterations and wall time when validation success first reached `level`."""
    for row in history:
        if row.get("eval_success", -1.0) >= level:
            return {k: row[k] for k in ("episodes", "iterations", "wall_s")}
    return None


def first_scans(world: WorldConfig, seed: int, count: int = 256) -> NDArray[np.float32]:
    """Encoded first scans (count, B) of `count` episodes of the world, layouts from `seed`."""
    state = reset(world, np.full(count, seed, dtype=np.int64), np.arange(count, dtype=np.int64))
    scan = observe(world, state).scan_m
    assert scan is not None
    return encode_scan(scan, distance_scale_m(world.lidar))


def _crossed(every: int, episodes: int, added: int) -> bool:
    """Whether the last `added` episodes passed a multiple of `every` (never if every is 0)."""
    return bool(every) and episodes // every > (episodes - added) // every


def _collect(
    world: WorldConfig, settings: TrainSettings, online: QNetwork, first: int, round_index: int
) -> list[Episode]:
    count = min(settings.parallel_worlds, settings.episodes - first)
    demonstrator = None
    if first < settings.demonstration_episodes:
        count = min(count, settings.demonstration_episodes - first)
        demonstrator = OracleDriver(world, seed=settings.seed * 1_000_000 + round_index).act
    ids = np.arange(first, first + count, dtype=np.int64)
    agent = policy_agent(
        online,
        world,
        count,
        settings.window,
        hold_steps=settings.hold_steps,
        seed=settings.seed * 1_000_000 + round_index,
    )
    agent.exploration.epsilon[:] = [settings.epsilon(int(i)) for i in ids]
    online.eval()
    return collect_round(
        world, agent, _TRAIN_LAYOUT_SEED + settings.seed, ids, demonstrator=demonstrator
    )


def _evaluate(
    world: WorldConfig,
    *,
    settings: TrainSettings,
    network: QNetwork,
    episodes: int,
    seed: int,
    max_steps: int,
) -> EvalResult:
    network.eval()
    eval_settings = EvalSettings(
        episodes=episodes, num_worlds=min(episodes, 100), seed=seed, max_episode_steps=max_steps
    )
    agent = policy_agent(network, world, eval_settings.num_worlds, settings.window)
    return evaluate(world, agent, eval_settings)


def _checkpoint(
    path: Path,
    online: QNetwork,
    target: QNetwork,
    optimizer: torch.optim.Optimizer,
    state: Progress,
    *,
    next_scan: NextScanLoss | None,
) -> None:
    partial = path.with_suffix(".partial")
    saved = {
        "online": online.state_dict(),
        "target": target.state_dict(),
        "optimizer": optimizer.state_dict(),
        "progress": asdict(state),
    }
    if next_scan is not None:
        saved["next_scan"] = next_scan.predictor.state_dict()
    torch.save(saved, partial)
    partial.replace(path)


def _write_progress(run_dir: Path, history: list[dict[str, float]], title: str) -> None:
    columns = [
        "episodes",
        "iterations",
        "wall_s",
        "epsilon",
        "train_success",
        "train_collision",
        "loss",
        "eval_success",
        "eval_collision",
        "eval_unfinished",
        "decisive_safe",
        "decisive_balanced",
    ]
    partial = run_dir / "progress.csv.partial"
    with partial.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, columns)
        writer.writeheader()
        writer.writerows(history)
    partial.replace(run_dir / "progress.csv")
    if "eval_success" in history[-1]:  # the picture changes only with a new evaluation
        from training.plots import plot_training

        plot_training(history, run_dir / "success.png", title)
