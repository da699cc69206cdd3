"""The training loop: collect a round, learn from the replay, evaluate, checkpoint; then test.

The pieces it runs, each in a module of its own:

    training.run_folder   the run's files: settings, checkpoints, episodes, progress, results
    training.collect      a round of episodes in parallel worlds, epsilon-greedy
    training.replay       storage of every collected episode
    training.sampling     how a batch is drawn: steps, targets and obstacles re-drawn
    training.algorithm    double DQN: the update, the target network, the optimiser
    training.validation   greedy evaluations during training

A run killed at any moment resumes from its last checkpoint when started again with the same
folder: rounds collected after that checkpoint are read back from `episodes/` and trained on.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import Outcome
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalSettings
from qnav.training.agent import policy_agent
from qnav.training.algorithm import DoubleDQN
from qnav.training.collect import collect_round
from qnav.training.config import TrainSettings
from qnav.training.episode_log import Episode
from qnav.training.imitation import Imitation
from qnav.training.networks import QNetwork, make_network
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import Progress, RunFolder, RunSettings, source_commit
from qnav.training.sampling import sample
from qnav.training.validation import Validation, evaluate_network, layout_tests

BARN_WORLDS = 300
"""BARN's worlds: a layout run's final test runs the first `final_eval_episodes` of them."""
REACHED_LEVELS = (0.5, 0.8, 0.9, 0.99)
"""Validation success levels whose first crossing results.json records."""
_TRAIN_LAYOUT_SEED = 1_000_003


def train(
    world: WorldConfig,
    settings: TrainSettings,
    run_dir: Path,
    progress: bool = True,
) -> dict[str, Any]:
    """Run (or resume) training in `run_dir`; returns the final test results."""
    if world.layout.source == "barn":
        raise ConfigError(
            "layout.source = 'barn': BARN's 300 worlds are the test set; train in generated "
            "worlds (the clutter scenario) and test on BARN with qnav eval --barn"
        )
    world = replace(world, max_episode_steps=settings.max_episode_steps)
    folder = RunFolder(run_dir)
    folder.start(RunSettings(world, settings))
    torch.set_num_threads(settings.threads)
    torch.manual_seed(settings.seed)
    dqn = DoubleDQN(make_network(world, settings), settings)
    state, logged, replay = _resume(folder, dqn, world, settings)
    validation = Validation(world, settings)
    title = f"{world.name}, {settings.model}, seed {settings.seed}"
    if state.imitation_rounds < settings.imitation.rounds:
        _imitate(
            world,
            settings=settings,
            dqn=dqn,
            folder=folder,
            state=state,
            validation=validation,
            title=title,
            progress=progress,
        )
    bar = tqdm(total=settings.episodes, initial=state.episodes, unit="ep",
               disable=not progress, desc=f"train {title}")  # fmt: skip
    while state.episodes < settings.episodes:
        round_index, started = state.rounds, time.perf_counter()
        if round_index < len(logged):
            episodes = logged[round_index]  # collected before a kill; already in the replay
        else:
            episodes = _collect(world, settings, dqn.online, state.episodes, round_index)
            folder.write_round(round_index, episodes)
            for episode in episodes:
                replay.add(episode)
        state.collect_s += time.perf_counter() - started
        state.episodes += len(episodes)
        state.rounds += 1

        started = time.perf_counter()
        losses = _learn(dqn, replay, settings, state, round_index)
        state.train_s += time.perf_counter() - started

        row = _round_row(settings, state, episodes, losses)
        if _crossed(settings.snapshot_every_episodes, state.episodes, len(episodes)):
            folder.save_snapshot(dqn.online, state)
        if _crossed(settings.eval_every_episodes, state.episodes, len(episodes)):
            started = time.perf_counter()
            row |= validation(dqn.online)
            if settings.keep_best and row["eval_success"] >= state.best_success:
                state.best_success = row["eval_success"]
                folder.save_best(dqn.online, state.episodes)
            state.eval_s += time.perf_counter() - started
        state.history.append(row)
        folder.save_checkpoint(dqn.state_dict(), state)
        folder.write_progress(state.history, title)
        bar.update(len(episodes))
        bar.set_postfix(eps=f"{row['epsilon']:.3f}", loss=f"{row['loss']:.4f}",
                        val=last_validation(state.history))  # fmt: skip
    bar.close()
    return folder.results() or _finish(world, settings, dqn, folder, state)


def last_validation(history: list[dict[str, float]]) -> str:
    """The progress bar's `val`: the last validation success so far, '-' before the first (a
    round without a validation showed nan)."""
    checked = [row["eval_success"] for row in history if "eval_success" in row]
    return f"{checked[-1]:.2f}" if checked else "-"


def _imitate(
    world: WorldConfig,
    *,
    settings: TrainSettings,
    dqn: DoubleDQN,
    folder: RunFolder,
    state: Progress,
    validation: Validation,
    title: str,
    progress: bool,
) -> None:
    """The imitation phase (`training.imitation`), resumed where a kill left it; the target
    network then starts from what was imitated."""
    imitation = Imitation(world, settings, dqn.online, dqn.optimizer, folder.path / "imitation")
    bar = tqdm(total=settings.imitation.rounds, initial=state.imitation_rounds, unit="round",
               disable=not progress, desc=f"imitate {title}")  # fmt: skip
    while state.imitation_rounds < settings.imitation.rounds:
        row = imitation.round(state.imitation_rounds, state)
        started = time.perf_counter()
        row |= validation(dqn.online)
        state.eval_s += time.perf_counter() - started
        if settings.keep_best and row["eval_success"] >= state.best_success:
            state.best_success = row["eval_success"]
            folder.save_best(dqn.online, row["episodes"])
        state.history.append(row)
        folder.save_checkpoint(dqn.state_dict(), state)
        folder.write_progress(state.history, title)
        bar.update(1)
        bar.set_postfix(loss=f"{row['loss']:.3f}", val=f"{row['eval_success']:.2f}")
    bar.close()
    dqn.target.load_state_dict(dqn.online.state_dict())


def _resume(
    folder: RunFolder, dqn: DoubleDQN, world: WorldConfig, settings: TrainSettings
) -> tuple[Progress, list[list[Episode]], EpisodeReplay]:
    """The run's counters (from its last checkpoint, whose networks and optimiser `dqn` takes
    up), every round collected so far, and a replay holding them all."""
    state = Progress()
    saved = folder.checkpoint(dqn.device)
    if saved is not None:
        dqn.load_state_dict(saved)
        state = Progress(**saved["progress"])
    capacity = settings.episodes * (settings.max_episode_steps + 1)
    replay = EpisodeReplay(world, capacity, settings.window)
    logged = folder.rounds()
    for episodes in logged:
        for episode in episodes:
            replay.add(episode)
    if sum(len(r) for r in logged) < state.episodes:
        raise ConfigError(f"{folder.episodes} holds fewer episodes than its checkpoint")
    return state, logged, replay


def _collect(
    world: WorldConfig, settings: TrainSettings, online: QNetwork, first: int, round_index: int
) -> list[Episode]:
    """The next round: up to `parallel_worlds` epsilon-greedy episodes, at once."""
    count = min(settings.parallel_worlds, settings.episodes - first)
    ids = np.arange(first, first + count, dtype=np.int64)
    agent = policy_agent(
        online,
        world,
        count,
        settings.window,
        seed=settings.seed * 1_000_000 + round_index,
    )
    agent.exploration.epsilon[:] = [settings.epsilon(int(i)) for i in ids]
    online.eval()
    return collect_round(world, agent, _TRAIN_LAYOUT_SEED + settings.seed, ids)


def _learn(
    dqn: DoubleDQN,
    replay: EpisodeReplay,
    settings: TrainSettings,
    state: Progress,
    round_index: int,
) -> list[float]:
    """The iterations owed once this round is in (`iterations_per_episode` for each episode
    after the warm-up ones); returns their losses."""
    owed = math.floor(
        settings.iterations_per_episode * max(0, state.episodes - settings.warmup_episodes)
    )
    rng = np.random.default_rng([settings.seed, round_index])
    losses = []
    dqn.online.train()
    while state.iterations < owed:
        batch = sample(
            replay,
            settings.batch_size,
            rng,
            settings.relabel,
            n_step=settings.n_step,
            gamma=settings.gamma,
            obstacle_redraw_probability=settings.obstacle_redraw_probability,
        )
        state.iterations += 1
        losses.append(dqn.update(batch, state.iterations).loss)
    return losses


def _round_row(
    settings: TrainSettings, state: Progress, episodes: list[Episode], losses: list[float]
) -> dict[str, float]:
    """progress.csv's row of a round, before any evaluation."""
    return {
        "episodes": state.episodes,
        "iterations": state.iterations,
        "wall_s": round(state.collect_s + state.train_s + state.eval_s, 2),
        "epsilon": round(settings.epsilon(state.episodes - 1), 4),
        "train_success": float(np.mean([e.outcome == Outcome.SUCCESS for e in episodes])),
        "train_collision": float(np.mean([e.outcome == Outcome.COLLISION for e in episodes])),
        "loss": float(np.mean(losses)) if losses else math.nan,
    }


def _finish(
    world: WorldConfig,
    settings: TrainSettings,
    dqn: DoubleDQN,
    folder: RunFolder,
    state: Progress,
) -> dict[str, Any]:
    """Ship the last network (or, with `keep_best`, the best validated one) as model.pt, test it
    under the paper's protocol, and write results.json."""
    best = folder.best(dqn.device) if settings.keep_best else None
    if best is not None:
        dqn.online.load_state_dict(best)
    folder.save_model(dqn.online.state_dict(), RunSettings(world, settings))
    started = time.perf_counter()
    tests: dict[str, Any] = {}
    if world.layout.source:
        tests = layout_tests(
            world,
            dqn.online,
            settings.window,
            settings.final_eval_episodes,
            settings.imitation.turn_commitment,
        )
        barn = tests["barn"]
        test = {
            "success": barn["success"],
            "collision": barn["collision"],
            "unfinished": barn["timeout"],
            "episodes": min(settings.final_eval_episodes, BARN_WORLDS),
        }
    else:
        protocol = EvalSettings()
        test = evaluate_network(
            world,
            dqn.online,
            settings.window,
            episodes=settings.final_eval_episodes,
            seed=protocol.seed,
            max_steps=protocol.max_episode_steps,
            turn_commitment=settings.imitation.turn_commitment,
        ).fractions()
    results = {
        "scenario": world.name,
        "model": settings.model,
        "seed": settings.seed,
        "relabel": settings.relabel,
        "test": test,
        **tests,
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
    folder.write_results(results)
    return results


def first_reached(history: list[dict[str, float]], level: float) -> dict[str, float] | None:
    """Episodes, iterations and wall time when validation success first reached `level`."""
    for row in history:
        if row.get("eval_success", -1.0) >= level:
            return {k: row[k] for k in ("episodes", "iterations", "wall_s")}
    return None


def _crossed(every: int, episodes: int, added: int) -> bool:
    """Whether the last `added` episodes passed a multiple of `every` (never if every is 0)."""
    return bool(every) and episodes // every > (episodes - added) // every
