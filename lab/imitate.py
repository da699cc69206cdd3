"""How well can the Q-network copy the oracle planner? A behaviour-cloning ceiling.

`qnav lab imitate --scenario S` collects episodes driven by the planner that knows the obstacles'
future (`lab.oracle.OracleDriver`), trains the learner's own network (recurrent or feedforward,
the paper's sizes) to pick the planner's action from the same windows of k observations the
policy sees (cross-entropy on its three outputs as logits), and runs the clone under the test
protocol. Nothing of reinforcement learning is involved, so the result separates two reasons a
DQN run can stall below the planner:

- the clone gets near the planner: the network and its inputs can hold a policy that good,
  and what is missing is in the learning (data, targets, optimisation);
- the clone stalls too: the window of observations, or the network reading it, is the limit.

It also measures the dodges: decisions where the planner does not do what the go-to-target
baseline (blind to obstacles, `sim.evaluate.go_to_target`) would. They are what separates the
planner from that baseline (about a third of its decisions with moving obstacles), and a copy
can agree on most decisions and still miss them; `dodge_weight` weighs them more in the copy's
loss.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn
from torch.nn import functional
from tqdm import tqdm

from qnav.contracts.motion import Outcome
from qnav.contracts.observation import TARGET_FEATURES
from qnav.lab.imitation_settings import ImitationSettings
from qnav.lab.oracle import OracleDriver
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, evaluate, go_to_target
from qnav.training.agent import policy_agent
from qnav.training.algorithm import cpu_has_bf16
from qnav.training.collect import collect_round
from qnav.training.episode_log import Episode
from qnav.training.networks import QNetwork
from qnav.training.replay import EpisodeReplay

DEMONSTRATION_LAYOUT_SEED = 555_555
"""Layouts of the demonstrations: neither the training runs', the validation's nor the test's."""
AGREEMENT_PROBE = 4096
"""Copied decisions drawn at random to measure the clone's agreement on them."""


@dataclass(frozen=True)
class ImitationResult:
    """The planner on the copied episodes, the clone's agreement with it, and the clone's test."""

    planner_success: float
    """Success of the planner's episodes that were copied (training layouts, up to 200 steps)."""
    windows: int
    """Windows (decisions) of the planner's episodes copied (DAgger's come on top)."""
    train_agreement: float
    """Share of `AGREEMENT_PROBE` copied windows on which the clone picks the planner's
    action."""
    held_out_agreement: float
    """The same on windows of the held-out planner episodes."""
    dodge_share: float
    """Share of the held-out decisions that are dodges (the planner's action is not the
    go-to-target baseline's)."""
    dodge_agreement: float
    """Share of those dodges on which the clone picks the planner's action."""
    dodge_as_baseline: float
    """Share of those dodges on which the clone picks the baseline's action instead."""
    test: EvalResult
    """The clone under the test protocol (greedy, 200 episodes of up to 500 steps)."""
    dagger: list[dict[str, float]]
    """Per DAgger round (0: the first copy): decisions copied so far, and the clone's test
    success after the round (empty without DAgger rounds)."""
    minutes: float
    """Wall time of the whole measurement."""
    planner_self_agreement: float | None = None
    """Share of the held-out states on which the planner, asked again with other random
    sequences, picks the action it took: how far its choice is a function of the state
    (measured by `--privileged` only)."""

    def to_dict(self) -> dict[str, Any]:
        """As JSON-ready values."""
        found = asdict(self)
        found["test"] = {k: v for k, v in found["test"].items() if k != "mean_steps"}
        return found


def collect_labelled(
    world: WorldConfig,
    *,
    count: int,
    first_episode: int,
    settings: ImitationSettings,
    copy: QNetwork | None = None,
    window: int = 0,
) -> list[Episode]:
    """`count` episodes with the layouts of episodes first_episode, ..., each state labelled
    with the planner's action (stored as the episodes' actions): driven by the planner itself,
    or, for DAgger, by `copy` (reading windows of `window` frames)."""
    world = replace(world, max_episode_steps=settings.max_episode_steps)
    driver = OracleDriver(world, seed=settings.seed + first_episode)
    layout_seed = DEMONSTRATION_LAYOUT_SEED + settings.seed
    episodes: list[Episode] = []
    desc = "planner episodes" if copy is None else "DAgger episodes"
    with tqdm(total=count, unit="ep", desc=desc, leave=False) as bar:
        while len(episodes) < count:
            start = first_episode + len(episodes)
            ids = np.arange(start, start + min(settings.parallel_worlds, count - len(episodes)))
            if copy is None:
                episodes += collect_round(world, None, layout_seed, ids, demonstrator=driver.act)
            else:
                agent = policy_agent(copy, world, ids.size, window)
                episodes += collect_round(world, agent, layout_seed, ids, labeller=driver.act)
            bar.update(ids.size)
    return episodes


def _windows(replay: EpisodeReplay) -> tuple[NDArray[Any], NDArray[Any]]:
    """Every decision of the replay: its window of k frames (own target, own obstacles) and
    the action taken."""
    now = np.flatnonzero(replay.last[: replay.size] > np.arange(replay.size))
    batch = replay.transitions_at(now, replay.own_target[now])
    return batch.frames[:, : replay.window], batch.action


def _replay_of(
    world: WorldConfig, episodes: list[Episode], settings: ImitationSettings, window: int
) -> EpisodeReplay:
    replay = EpisodeReplay(world, len(episodes) * (settings.max_episode_steps + 1), window)
    for episode in episodes:
        replay.add(episode)
    return replay


def baseline_actions(frames: NDArray[Any]) -> NDArray[np.int64]:
    """The go-to-target baseline's action on each window (N, k, F), from its last frame."""
    return go_to_target(frames[:, -1, -TARGET_FEATURES:])


def clone(
    network: nn.Module,
    optimizer: torch.optim.Optimizer,
    *,
    inputs: NDArray[Any],
    actions: NDArray[Any],
    baseline: NDArray[np.int64],
    settings: ImitationSettings,
    rng: np.random.Generator,
) -> None:
    """`settings.iterations` cross-entropy steps on random rows of (inputs, actions), dodges
    (where `actions` are not the go-to-target `baseline`'s) weighted by `settings.dodge_weight`."""
    bf16 = cpu_has_bf16()
    weights = np.where(actions != baseline, settings.dodge_weight, 1.0)
    network.train()
    for _ in tqdm(range(settings.iterations), unit="it", desc="cloning", leave=False):
        rows = rng.integers(0, actions.size, settings.batch_size)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            logits = network(torch.from_numpy(inputs[rows])).float()
        losses = functional.cross_entropy(logits, torch.from_numpy(actions[rows]), reduction="none")
        weight = torch.from_numpy(weights[rows]).float()
        loss = (losses * weight).sum() / weight.sum()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()  # type: ignore[no-untyped-call]
        optimizer.step()
    network.eval()


def _test(
    world: WorldConfig, network: QNetwork, settings: ImitationSettings, window: int
) -> EvalResult:
    worlds = min(100, settings.test_episodes)
    return evaluate(
        world,
        policy_agent(network, world, worlds, window),
        EvalSettings(episodes=settings.test_episodes, num_worlds=worlds),
    )


def greedy_choices(network: nn.Module, inputs: NDArray[Any]) -> NDArray[np.int64]:
    """The network's highest-scoring action on each row of `inputs`."""
    with torch.no_grad():
        return network(torch.from_numpy(inputs)).argmax(dim=1).numpy()  # type: ignore[no-any-return]


def fraction_true(flags: NDArray[np.bool_]) -> float:
    """The share of true flags (0 of none)."""
    return float(np.mean(flags)) if flags.size else 0.0


def held_out_counts(
    chosen: NDArray[np.int64], planner: NDArray[np.int64], baseline: NDArray[np.int64]
) -> dict[str, float]:
    """`ImitationResult`'s held-out agreement and dodge counts from the clone's, the planner's
    and the go-to-target baseline's actions on the held-out decisions."""
    dodges = planner != baseline
    return {
        "held_out_agreement": fraction_true(chosen == planner),
        "dodge_share": fraction_true(dodges),
        "dodge_agreement": fraction_true(chosen[dodges] == planner[dodges]),
        "dodge_as_baseline": fraction_true(chosen[dodges] == baseline[dodges]),
    }


def imitate(world: WorldConfig, settings: ImitationSettings, window: int) -> ImitationResult:
    """Collect, clone, test (module docstring)."""
    started = time.perf_counter()
    torch.set_num_threads(settings.threads)
    torch.manual_seed(settings.seed)
    copied = collect_labelled(world, count=settings.episodes, first_episode=0, settings=settings)
    held_out = collect_labelled(
        world,
        count=settings.held_out_episodes,
        first_episode=settings.episodes,
        settings=settings,
    )
    frames, actions = _windows(_replay_of(world, copied, settings, window))
    held_frames, held_actions = _windows(_replay_of(world, held_out, settings, window))

    network = QNetwork(settings.model, world.lidar.num_beams if world.lidar else None)
    optimizer = torch.optim.Adam(network.parameters(), lr=settings.learning_rate)
    rng = np.random.default_rng(settings.seed)
    copied_windows = actions.size
    train_agreement = 0.0
    dagger: list[dict[str, float]] = []
    first = settings.episodes + settings.held_out_episodes
    for round_index in range(settings.dagger_rounds + 1):  # round 0: the copy of the planner
        if round_index:
            corrected = collect_labelled(
                world,
                count=settings.dagger_episodes,
                first_episode=first,
                settings=settings,
                copy=network,
                window=window,
            )
            first += settings.dagger_episodes
            more_frames, more_actions = _windows(_replay_of(world, corrected, settings, window))
            frames = np.concatenate([frames, more_frames])
            actions = np.concatenate([actions, more_actions])
        clone(
            network,
            optimizer,
            inputs=frames,
            actions=actions,
            baseline=baseline_actions(frames),
            settings=settings,
            rng=rng,
        )
        if not round_index:
            probe = rng.integers(0, actions.size, AGREEMENT_PROBE)
            train_agreement = fraction_true(
                greedy_choices(network, frames[probe]) == actions[probe]
            )
        test = _test(world, network, settings, window)
        if settings.dagger_rounds:
            dagger.append(
                {"round": round_index, "windows": actions.size, "test_success": test.success}
            )
    return ImitationResult(
        planner_success=float(np.mean([e.outcome == Outcome.SUCCESS for e in copied])),
        windows=int(copied_windows),
        train_agreement=train_agreement,
        **held_out_counts(
            greedy_choices(network, held_frames), held_actions, baseline_actions(held_frames)
        ),
        test=test,
        dagger=dagger,
        minutes=round((time.perf_counter() - started) / 60, 1),
    )
