"""How far the Q-network can perceive doom: a ceiling for learning the decisive moments.

RL hears that an action was doomed only through a collision many steps later, under a re-drawn
target and obstacles. This probe removes all of that: the paper's network is trained by plain
supervision on the planner's per-action doom labels (is each first action doomed, `lab.oracle`)
of windows from planner and go-to-target episodes, then judged on the gauge's held-out decisive
states (`lab.decisive`). If it cannot pick safe actions there, no replay scheme or loss
weighting on top of RL will teach the same network from the same amount of experience: the
limit is perception. `qnav lab probe` runs it.

With `probe.shield_episodes`, the fitted network is then put to work where its judgement
matters: it shields go-to-target on the test protocol (keeping go-to-target's action unless it
judges that action doomed), beside go-to-target alone and go-to-target shielded by the exact
labels it was fitted to. That turns a gauge figure into success: how good a doom judgement
must be before it moves the outcome.

The probe is a diagnostic: nothing in training or the product imports it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
import torch
from numpy.typing import NDArray
from tqdm import tqdm

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.errors import ConfigError
from qnav.contracts.judge_file import judge_inputs, judged_actions
from qnav.contracts.observation import (
    OBSTACLE_SLOT_FEATURES,
    TARGET_FEATURES,
    FrameWindow,
    distance_scale_m,
    encode_frame,
    encode_target,
)
from qnav.contracts.policy_file import CONV_CHANNELS
from qnav.contracts.settings import check_range
from qnav.lab.decisive import DecisiveStates, GaugeSettings, cached, is_decisive, score
from qnav.lab.oracle import PERCEIVED, collision_shares, doom_label_safety
from qnav.lab.redrawn import redrawn_states
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, WanderingGoToTarget, drive, go_to_target
from qnav.sim.world import BatchedWorld, Observation, WorldState, observe
from qnav.training.agent import greedy_actions
from qnav.training.networks import QNetwork, conv_layers, conv_output_length, lstm_last_output


@dataclass(frozen=True)
class ProbeSettings:
    """The labelled set and the supervised fit."""

    SECTION = "probe"

    episodes_per_driver: int = 300
    """Episodes driven by each of the planner and go-to-target for the training set."""
    ordinary_share: float = 0.3
    """Share of non-decisive states (all actions safe, or all doomed) kept beside every
    decisive one."""
    seed: int = 778
    """Layout seed of the training set (the gauge's own is 31,337)."""
    epochs: int = 10
    """Passes over the training set."""
    batch_size: int = 128
    """Windows per gradient step."""
    learning_rate: float = 1e-3
    """Adam's learning rate."""
    decisive_weight: float = 3.0
    """Weight of a decisive window's loss against an ordinary one's."""
    inputs: Literal["lidar", "state", "slots"] = "lidar"
    """What the fitted network sees: "lidar" (the paper's network on the policy's window),
    "state" (the exact world state, per obstacle, through `ObstacleSetNetwork`): the state
    probe bounds what the labels teach when perception is perfect; or "slots" (the same
    structure on what a network given obstacle inputs sees, `slot_features`)."""
    label: Literal["doom", "collide_share", "outcome"] = "doom"
    """What it is fitted to per action: "doom" (0/1: every continuation collides),
    "collide_share" (the share of continuations that collide, graded) or "outcome" (whether one
    continuation, drawn by that share, collides: all that one experienced return can tell)."""
    labelled_actions: Literal["all", "random", "taken"] = "all"
    """Whose labels each state gives: "all" (every action's), "random" (one action's, drawn
    uniformly: what a stored step among re-drawn obstacles shows) or "taken" (the action the
    driver took there: what its own experience shows)."""
    redrawn_from: str = ""
    """A training run folder: fit to `redrawn_states` of its own stored steps, each among freshly
    drawn obstacles and labelled by the planner (`lab.redrawn`), instead of the episodes driven
    by the planner and go-to-target ("": those; inputs "state" or "slots" only). In `qnav lab
    label` its rounds too draw re-drawn states at the run's stored steps instead of driving."""
    redrawn_states: int = 100_000
    """Stored steps labelled among re-drawn obstacles with `redrawn_from` (about 3 % of them
    are decisive; 4 ms of CPU each); in `qnav lab label` each later round draws as many and
    labels the most doubtful `doubt.labelled_share` of them."""
    shield_episodes: int = 0
    """Test-protocol episodes in which the fitted network then shields go-to-target, beside
    go-to-target alone and shielded by the exact labels (0: no shield test; inputs "state" or
    "slots" only)."""
    threads: int = 2
    """Torch threads."""

    def __post_init__(self) -> None:
        check_range(self, "episodes_per_driver", self.episodes_per_driver, 1, 10**7)
        check_range(self, "shield_episodes", self.shield_episodes, 0, 10**7)
        if self.shield_episodes and self.inputs == "lidar":
            raise ConfigError(
                "probe.shield_episodes needs probe.inputs = state or slots: the shield judges "
                "each step from the state, without a window of scans"
            )
        if self.redrawn_from and self.inputs == "lidar":
            raise ConfigError(
                "probe.redrawn_from needs probe.inputs = state or slots: re-drawn obstacles are "
                "labelled without rendering their scans"
            )
        check_range(self, "redrawn_states", self.redrawn_states, 1, 10**9)
        check_range(self, "ordinary_share", self.ordinary_share, 0.0, 1.0)
        check_range(self, "epochs", self.epochs, 1, 10**6)
        check_range(self, "batch_size", self.batch_size, 1, 10**6)
        check_range(self, "learning_rate", self.learning_rate, 0.0, 1.0, exclusive_low=True)
        check_range(self, "decisive_weight", self.decisive_weight, 0.0, 1e6)
        check_range(self, "threads", self.threads, 1, 1024)

    def labelled_set(self, gauge: GaugeSettings) -> GaugeSettings:
        """The labelled set's collection: this probe's episodes, seed and ordinary share, with
        the gauge's episode length and window."""
        return GaugeSettings(
            episodes_per_driver=self.episodes_per_driver,
            max_episode_steps=gauge.max_episode_steps,
            seed=self.seed,
            window=gauge.window,
            ordinary_share=self.ordinary_share,
        )


class ProbeEpoch(NamedTuple):
    """The fit after one pass over the training set."""

    epoch: int
    """1-based pass."""
    loss: float
    """Mean weighted binary cross-entropy of the pass."""
    train_balanced: float
    """Balanced gauge score on the training set's own decisive states (does it fit?)."""
    safe: float
    """Share of the held-out gauge states where the network's choice is safe."""
    balanced: float
    """The same averaged over doom patterns (1/2 for any choice blind to the scan)."""


def decisive_only(states: DecisiveStates) -> DecisiveStates:
    """The states of a set where some action is doomed and another is not."""
    return states.subset(is_decisive(states.doomed))


def state_features(world: WorldState, arena_size_m: float) -> tuple[NDArray[np.float32], ...]:
    """The exact state as a perceiver of it would give it: (context (K, 8), obstacles (K, M, 7)).

    Context: the robot's speed and turn rate, the target in the robot's frame, the robot's
    position in the arena and its heading (for the walls). Per obstacle: its position and
    velocity in the robot's frame, its distance, and its place in the arena (for its bounces).
    Lengths are in units of half the arena.
    """
    half = arena_size_m / 2
    pose = world.pose
    cos, sin = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    to_robot = np.stack([np.stack([cos, sin], -1), np.stack([-sin, cos], -1)], axis=1)
    offset = world.obstacle_xy - pose[:, None, :2]
    context = np.concatenate(
        [
            world.velocity,
            np.einsum("kij,kj->ki", to_robot, world.target_xy - pose[:, :2]) / half,
            pose[:, :2] / half - 1,
            np.stack([cos, sin], axis=-1),
        ],
        axis=1,
    )
    obstacles = np.concatenate(
        [
            np.einsum("kij,kmj->kmi", to_robot, offset) / half,
            np.einsum("kij,kmj->kmi", to_robot, world.obstacle_velocity),
            np.linalg.norm(offset, axis=-1, keepdims=True) / half,
            world.obstacle_xy / half - 1,
        ],
        axis=2,
    )
    return context.astype(np.float32), obstacles.astype(np.float32)


def slot_features(states: DecisiveStates) -> tuple[NDArray[np.float32], ...]:
    """What a network given obstacle inputs sees in its newest frame, split as the state probe's
    inputs: (context (K, 5), obstacles (K, OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES)). Context:
    the robot's own speed and turn rate (which the car estimates from its poses) and the encoded
    target; per obstacle, its slot of `contracts.observation.obstacle_features`."""
    return judge_inputs(
        states.world.velocity,
        states.windows[:, -1, -TARGET_FEATURES:],
        states.obstacle_windows[:, -1],
    )


def labelled_features(
    world: WorldConfig, inputs: str, states: DecisiveStates
) -> tuple[NDArray[np.float32], ...]:
    """What a doom network with `ProbeSettings.inputs` "state" or "slots" sees in a labelled
    set's states (`state_inputs` for worlds being driven)."""
    if inputs == "state":
        return state_features(states.world, world.arena.size_m)
    return slot_features(states)


class ObstacleSetNetwork(torch.nn.Module):
    """Doom from exact state, one source at a time: a network shared by all obstacles gives each
    obstacle's logit of dooming each action, another the walls' from the context alone, and an
    action is safe when no source dooms it. Sharing across obstacles is the structure a lidar
    convolution shares across bearings."""

    def __init__(self, context_size: int = 8, obstacle_size: int = 7, hidden: int = 128) -> None:
        super().__init__()
        self.per_obstacle = torch.nn.Sequential(
            torch.nn.Linear(context_size + obstacle_size, hidden),
            torch.nn.ReLU(),
            torch.nn.Linear(hidden, hidden),
            torch.nn.ReLU(),
            torch.nn.Linear(hidden, NUM_ACTIONS),
        )
        self.walls = torch.nn.Sequential(
            torch.nn.Linear(context_size, hidden // 2),
            torch.nn.ReLU(),
            torch.nn.Linear(hidden // 2, NUM_ACTIONS),
        )

    def forward(self, context: torch.Tensor, obstacles: torch.Tensor) -> torch.Tensor:
        """(K, A) logits that each action is safe."""
        shared = context[:, None, :].expand(-1, obstacles.shape[1], -1)
        doom = torch.cat(
            [
                self.per_obstacle(torch.cat([shared, obstacles], dim=-1)),
                self.walls(context)[:, None],
            ],
            dim=1,
        )
        log_safe = torch.nn.functional.logsigmoid(-doom).sum(dim=1)
        # logit(p) = log p - log(1 - p), with p = P(no source dooms the action)
        return log_safe - torch.log(-torch.expm1(log_safe).clamp(max=-1e-6))


class Probe(NamedTuple):
    """A finished fit."""

    history: list[ProbeEpoch]
    """The fit and the gauge after each pass."""
    network: torch.nn.Module
    """The fitted network: logits that each action is safe (in eval mode)."""
    labelled_states: int = 0
    """States in the labelled set it was fitted to."""
    labelled_decisive: int = 0
    """Decisive states among them."""
    held_out_decisive: int = 0
    """Decisive states of the held-out gauge it is judged on."""


def doom_network(world: WorldConfig, inputs: str) -> torch.nn.Module:
    """A fresh network judging each action's doom from `ProbeSettings.inputs`."""
    if inputs == "state":
        return ObstacleSetNetwork()
    if inputs == "slots":
        return ObstacleSetNetwork(TARGET_FEATURES + 2, OBSTACLE_SLOT_FEATURES)
    return QNetwork("recurrent", world.lidar.num_beams if world.lidar is not None else None)


def fitted_labels(
    collide_share: NDArray[np.floating],
    settings: ProbeSettings,
    taken: NDArray[np.integer] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(K, A) the targets that each action is safe, as `settings.label` reads the collision
    shares, and (K, A) which of them the fit sees (`settings.labelled_actions`; "taken" needs
    the drivers' actions `taken` (K,)), both drawn from `settings.seed`."""
    chance = np.random.default_rng([settings.seed, 1])
    count, actions = collide_share.shape
    if settings.label == "doom":
        unsafe = np.asarray(collide_share == 1.0, dtype=np.float32)
    elif settings.label == "outcome":
        unsafe = (chance.random(collide_share.shape) < collide_share).astype(np.float32)
    else:
        unsafe = np.asarray(collide_share, dtype=np.float32)
    seen = np.ones((count, actions), dtype=np.float32)
    if settings.labelled_actions != "all":
        if settings.labelled_actions == "random":
            one = np.asarray(chance.integers(0, actions, count), dtype=np.int64)
        elif taken is None:
            raise ConfigError(
                "probe.labelled_actions = taken needs the actions the drivers took, which only "
                "`qnav lab probe`'s labelled set records"
            )
        else:
            one = np.asarray(taken, dtype=np.int64)
        seen = np.zeros_like(seen)
        seen[np.arange(count), one] = 1.0
    return 1.0 - unsafe, seen


def fit_doom(
    network: torch.nn.Module,
    inputs: tuple[torch.Tensor, ...],
    collide_share: NDArray[np.floating],
    settings: ProbeSettings,
    *,
    taken: NDArray[np.integer] | None = None,
    after_epoch: Callable[[int, float], None] | None = None,
    progress: bool = False,
) -> None:
    """Fit `network` (logits that each action is safe) to the labels of the states `inputs`
    describe (their (K, A) collision shares, as `fitted_labels` reads them), decisive states
    weighted by `settings.decisive_weight`; `after_epoch(epoch, mean loss)` is called after each
    pass with the network in eval mode."""
    target, seen = (
        torch.from_numpy(part) for part in fitted_labels(collide_share, settings, taken)
    )
    weight = torch.from_numpy(
        np.where(is_decisive(collide_share == 1.0), settings.decisive_weight, 1.0).astype(
            np.float32
        )
    )
    optimizer = torch.optim.Adam(network.parameters(), lr=settings.learning_rate)
    order = np.random.default_rng(settings.seed)
    for epoch in tqdm(range(1, settings.epochs + 1), desc="fit", disable=not progress):
        network.train()
        total = 0.0
        permutation = order.permutation(len(target))
        for start in range(0, len(target), settings.batch_size):
            rows = torch.from_numpy(permutation[start : start + settings.batch_size])
            per_label = torch.nn.functional.binary_cross_entropy_with_logits(
                network(*(part[rows] for part in inputs)), target[rows], reduction="none"
            )
            per_window = (per_label * seen[rows]).sum(dim=1) / seen[rows].sum(dim=1)
            loss = (per_window * weight[rows]).sum() / weight[rows].sum()
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
            total += loss.item() * len(rows)
        network.eval()
        if after_epoch is not None:
            after_epoch(epoch, total / len(target))


def labelled_states(
    world: WorldConfig, settings: ProbeSettings, gauge: GaugeSettings, progress: bool = False
) -> DecisiveStates:
    """The labelled states the probe fits: `settings.redrawn_from`'s stored steps among re-drawn
    obstacles, or the driven set (from the cache; `gauge` gives its episode length and window)."""
    if not settings.redrawn_from:
        return cached(world, settings.labelled_set(gauge), progress)
    return redrawn_states(
        world,
        Path(settings.redrawn_from),
        settings.redrawn_states,
        window=gauge.window,
        ordinary_share=settings.ordinary_share,
        seed=settings.seed,
        progress=progress,
    )


def probe(
    world: WorldConfig,
    settings: ProbeSettings = ProbeSettings(),
    gauge: GaugeSettings | None = None,
    progress: bool = False,
) -> Probe:
    """Fit a network to doom labels and judge it on the gauge after each pass."""
    gauge = gauge or GaugeSettings()
    torch.set_num_threads(settings.threads)
    labelled = labelled_states(world, settings, gauge, progress)
    held_out = cached(world, gauge, progress)
    fitted = decisive_only(labelled)
    torch.manual_seed(settings.seed)
    network = doom_network(world, settings.inputs)

    def inputs(states: DecisiveStates) -> tuple[torch.Tensor, ...]:
        if settings.inputs != "lidar":
            features = labelled_features(world, settings.inputs, states)
            return tuple(torch.from_numpy(part) for part in features)
        return (torch.from_numpy(states.windows),)

    def choices(states: DecisiveStates) -> NDArray[np.int64]:
        if isinstance(network, QNetwork):
            return greedy_actions(network, states.windows)
        with torch.no_grad():
            return np.asarray(network(*inputs(states)).argmax(dim=1).numpy(), dtype=np.int64)

    history = []

    def judge(epoch: int, loss: float) -> None:
        judged = score(held_out, choices(held_out))
        fit = score(fitted, choices(fitted))
        history.append(ProbeEpoch(epoch, loss, fit.balanced, judged.safe, judged.balanced))

    fit_doom(
        network,
        inputs(labelled),
        labelled.collide_share,
        settings,
        taken=labelled.taken,
        after_epoch=judge,
        progress=progress,
    )
    return Probe(
        history,
        network,
        labelled_states=len(labelled.doomed),
        labelled_decisive=len(fitted.doomed),
        held_out_decisive=int(is_decisive(held_out.doomed).sum()),
    )


class ShieldTest(NamedTuple):
    """Go-to-target on the test protocol, alone and shielded by two doom judgements."""

    blind: EvalResult
    """Go-to-target alone (blind to the obstacles)."""
    fitted: EvalResult
    """Shielded by the fitted network (`contracts.judge_file.judged_actions`)."""
    fitted_overruled: float
    """Share of the fitted shield's decisions that overrule go-to-target."""
    exact: EvalResult
    """Shielded by the exact labels the network was fitted to, from the planner's collision
    shares: doom (every continuation collides; where go-to-target's action is doomed, the least
    colliding action is taken) or the share itself."""
    exact_overruled: float
    """Share of the exact shield's decisions that overrule go-to-target."""
    tracked: EvalResult | None = None
    """Shielded by the fitted network on the onboard tracker's estimate, as a car would ask it
    (`tracked_safety`; inputs "slots" only, else None)."""
    tracked_overruled: float = 0.0
    """Share of the tracked shield's decisions that overrule go-to-target."""


SafeProbability = Callable[[WorldState, Observation], NDArray[np.floating]]
"""Each action's probability of being safe (N, A) in each world."""


def tracked_safety(
    world: WorldConfig, network: torch.nn.Module, range_noise_m: float = 0.0, seed: int = 0
) -> SafeProbability:
    """`network_safety` for slot inputs as a car asks it: the robot's velocity and the obstacles'
    slots come from the onboard tracker (`controller.lookahead.Lookahead`, one per episode, fed
    the simulated poses and scans, with Gaussian range noise of `range_noise_m` drawn from
    `seed`), not from the world's truth."""
    from qnav.controller.lookahead import Lookahead, LookaheadSettings, beliefs_inputs
    from qnav.controller.perception import TrackerSettings
    from qnav.tracking import noisy, world_lookahead

    cars: dict[int, Lookahead] = {}
    max_range_m = distance_scale_m(world.lidar)
    random = np.random.default_rng(seed)

    def safety(state: WorldState, observation: Observation) -> NDArray[np.floating]:
        assert observation.scan_m is not None  # world_lookahead refuses a world without lidar
        scans_m = noisy(observation.scan_m, range_noise_m, random)
        beliefs = []
        running = state.episode.tolist()
        for ended in cars.keys() - set(running):  # drive drops the worlds whose episode ended
            del cars[ended]
        for row, episode in enumerate(running):
            car = cars.get(episode)
            if car is None:
                car = world_lookahead(world, LookaheadSettings(mode="shield"), TrackerSettings())
                cars[episode] = car
            time_s = float(state.steps[row]) * world.control_period_s
            car.observe(time_s, observation.pose[row], time_s, scans_m[row])
            beliefs.append(car.belief(observation.target_xy[row]))
        parts = beliefs_inputs(beliefs, max_range_m)
        return judged_safe(network, parts)

    return safety


def shield_test(
    world: WorldConfig,
    fitted: Probe,
    settings: ProbeSettings,
    protocol: EvalSettings | None = None,
    progress: bool = False,
) -> ShieldTest:
    """Go-to-target on the test protocol alone, shielded by the fitted network, and shielded
    by the exact labels (`ShieldTest`), on the same layouts."""
    protocol = protocol or EvalSettings(episodes=settings.shield_episodes)
    fitted_safety = network_safety(world, fitted.network, settings.inputs)

    def exact_safety(state: WorldState, observation: Observation) -> NDArray[np.floating]:
        share = collision_shares(world, state)
        if settings.label == "collide_share":
            return 1.0 - share
        return doom_label_safety(share)

    shields: list[SafeProbability | None] = [None, fitted_safety, exact_safety]
    if settings.inputs == "slots":
        shields.append(tracked_safety(world, fitted.network))
    results = [
        shielded_go_to_target(world, shield, protocol)
        for shield in tqdm(shields, desc="shield test", unit="shield", disable=not progress)
    ]
    (blind, _), (with_network, network_overruled), (with_labels, labels_overruled), *on_car = (
        results
    )
    tracked, tracked_overruled = on_car[0] if on_car else (None, 0.0)
    return ShieldTest(
        blind,
        with_network,
        network_overruled,
        with_labels,
        labels_overruled,
        tracked,
        tracked_overruled,
    )


def state_inputs(
    world: WorldConfig, inputs: str, state: WorldState, observation: Observation
) -> tuple[NDArray[np.float32], ...]:
    """What a doom network with `ProbeSettings.inputs` "state" or "slots" sees in each world."""
    if inputs == "state":
        return state_features(state, world.arena.size_m)
    return judge_inputs(
        state.velocity,
        encode_target(observation.target_features(), distance_scale_m(world.lidar)),
        observation.obstacle_features(),
    )


def judged_safe(
    network: torch.nn.Module, parts: tuple[NDArray[np.float32], ...]
) -> NDArray[np.float64]:
    """(N, A) the fitted network's probabilities that each action is safe, given its inputs."""
    with torch.no_grad():
        logits = network(*(torch.from_numpy(part) for part in parts))
    return np.asarray(torch.sigmoid(logits).numpy(), dtype=np.float64)


def network_safety(world: WorldConfig, network: torch.nn.Module, inputs: str) -> SafeProbability:
    """The fitted network's probabilities that each action is safe, as a shield asks them."""

    def safety(state: WorldState, observation: Observation) -> NDArray[np.floating]:
        return judged_safe(network, state_inputs(world, inputs, state, observation))

    return safety


def shielded_go_to_target(
    world: WorldConfig,
    safety: SafeProbability | None,
    protocol: EvalSettings,
    threshold: float = 0.5,
) -> tuple[EvalResult, float]:
    """The protocol's episodes driven by go-to-target under `safety`'s shield (None: none;
    go-to-target's action kept where judged safe above `threshold`), and the share of decisions
    it overruled."""
    decisions = overruled = 0

    def act(state: WorldState, observation: Observation) -> NDArray[np.int64]:
        nonlocal decisions, overruled
        preferred = go_to_target(observation.target_features())
        if safety is None:
            return preferred
        chosen = judged_actions(preferred, safety(state, observation), threshold)
        decisions += chosen.size
        overruled += int((chosen != preferred).sum())
        return chosen

    config = replace(world, max_episode_steps=protocol.max_episode_steps)
    outcomes, steps = drive(config, protocol.seed, np.arange(protocol.episodes), act)
    return EvalResult.of_outcomes(outcomes, steps), overruled / max(decisions, 1)


@dataclass(frozen=True)
class PerceptionSettings:
    """Windows and fit of the perception probe (`qnav lab probe --perception`)."""

    SECTION = "perception"

    windows: int = 30_000
    """Training windows (each with the nearest obstacle within `max_distance_m`)."""
    held_out_windows: int = 4_000
    """Windows it is judged on, from other layouts."""
    max_distance_m: float = 4.0
    """Windows whose nearest obstacle is farther than this are skipped (4 s of the robot's
    reach plus an obstacle's: what matters for doom)."""
    explore_share: float = 0.3
    """Share of steps where a held random action replaces go-to-target's, so windows show
    turns and stops too."""
    epochs: int = 12
    """Passes over the training windows."""
    batch_size: int = 128
    """Windows per gradient step."""
    learning_rate: float = 1e-3
    """Adam's learning rate."""
    conv_channels: int = CONV_CHANNELS
    """Channels of each of the encoder's three convolutions (the paper: 8; policy files fix 8,
    so only this probe's `PerceptionNetwork` widens them)."""
    seed: int = 5
    """Seed of the training layouts and the fit; the held-out layouts use seed + 1000."""
    threads: int = 2
    """Torch threads."""

    def __post_init__(self) -> None:
        check_range(self, "windows", self.windows, 1, 10**7)
        check_range(self, "held_out_windows", self.held_out_windows, 1, 10**7)
        check_range(self, "max_distance_m", self.max_distance_m, 0.0, 1e3, exclusive_low=True)
        check_range(self, "explore_share", self.explore_share, 0.0, 1.0)
        check_range(self, "epochs", self.epochs, 1, 10**6)
        check_range(self, "batch_size", self.batch_size, 1, 10**6)
        check_range(self, "learning_rate", self.learning_rate, 0.0, 1.0, exclusive_low=True)
        check_range(self, "conv_channels", self.conv_channels, 1, 4096)
        check_range(self, "threads", self.threads, 1, 1024)


class PerceptionNetwork(torch.nn.Module):
    """The paper's recurrent network up to the window's summary (three convolutions per scan,
    an LSTM over the window), with `channels` per convolution: policy files fix the paper's 8
    (`training.networks.LidarEncoder`), this probe may widen them."""

    def __init__(self, num_beams: int, channels: int, hidden_size: int = 512) -> None:
        super().__init__()
        self.num_beams = num_beams
        self.convolutions = conv_layers(channels)
        features = channels * conv_output_length(num_beams) + TARGET_FEATURES
        self.lstm = torch.nn.LSTM(features, hidden_size, batch_first=True)
        self.summary_size = hidden_size

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, k, F) windows of frames -> (N, hidden_size): the LSTM's last output."""
        n, k, _ = frames.shape
        scans = frames[..., : self.num_beams].reshape(n * k, 1, self.num_beams)
        encoded = self.convolutions(scans).flatten(1).reshape(n, k, -1)
        features = torch.cat([encoded, frames[..., self.num_beams :]], dim=-1)
        return lstm_last_output(self.lstm, features)


class PerceptionEpoch(NamedTuple):
    """Median absolute errors on the held-out windows after one pass, by `PERCEIVED` name."""

    epoch: int
    """1-based pass (0: predicting the training mean, the blind baseline)."""
    loss: float
    """Mean squared error of the pass, in standard deviations (nan for the baseline)."""
    errors: dict[str, float]
    """Median absolute error of each perceived quantity, in its unit."""


def perception_windows(
    world: WorldConfig, count: int, settings: PerceptionSettings, seed: int
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """`count` windows (count, k, F) from go-to-target driving with held random actions, and
    the quantities (count, len(PERCEIVED)) they should reveal."""
    worlds = 200
    batched = BatchedWorld(world, worlds, seed=seed)
    observation = observe(world, batched.state)
    window = FrameWindow(worlds, world.lidar.num_beams + 3 if world.lidar else 3)
    driver = WanderingGoToTarget(worlds, settings.explore_share, seed)
    windows, truths = [], []
    found = 0
    while found < count:
        frames = window.advance(
            encode_frame(
                observation.scan_m, observation.target_features(), distance_scale_m(world.lidar)
            )
        )
        context, obstacles = state_features(batched.state, 2.0)  # lengths in metres
        nearest = np.argmin(obstacles[:, :, 4], axis=1)
        closest = obstacles[np.arange(worlds), nearest]
        keep = closest[:, 4] <= settings.max_distance_m
        windows.append(frames[keep].copy())
        truths.append(np.concatenate([closest[:, :4], context[:, :2]], axis=1)[keep])
        found += int(keep.sum())
        result = batched.step(driver(observation.target_features()))
        observation = result.observation
        window.restart(np.flatnonzero(result.transition.terminated | result.transition.truncated))
    return np.concatenate(windows)[:count], np.concatenate(truths)[:count].astype(np.float32)


def perceive(
    world: WorldConfig, settings: PerceptionSettings = PerceptionSettings(), progress: bool = False
) -> list[PerceptionEpoch]:
    """Fit the paper's recurrent network (its encoder and LSTM, with a linear head in place of
    the Q head) to regress `PERCEIVED` from windows; the first entry is the blind baseline."""
    if world.lidar is None or not world.obstacles.count:
        raise ConfigError(f"scenario {world.name!r} has no lidar and moving obstacles to perceive")
    torch.set_num_threads(settings.threads)
    windows, truth = perception_windows(world, settings.windows, settings, settings.seed)
    held_windows, held_truth = perception_windows(
        world, settings.held_out_windows, settings, settings.seed + 1000
    )
    mean, spread = truth.mean(axis=0), truth.std(axis=0) + 1e-6

    def errors(predicted: NDArray[np.float32]) -> dict[str, float]:
        median = np.median(np.abs(predicted - held_truth), axis=0)
        return dict(zip(PERCEIVED, median.tolist(), strict=True))

    history = [PerceptionEpoch(0, math.nan, errors(np.broadcast_to(mean, held_truth.shape)))]
    torch.manual_seed(settings.seed)
    network = PerceptionNetwork(world.lidar.num_beams, settings.conv_channels)
    head = torch.nn.Linear(network.summary_size, len(PERCEIVED))
    optimizer = torch.optim.Adam(
        [*network.parameters(), *head.parameters()], lr=settings.learning_rate
    )

    def predict(frames: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(head(network(frames)))

    inputs = torch.from_numpy(windows)
    targets = torch.from_numpy((truth - mean) / spread)
    order = np.random.default_rng(settings.seed)
    for epoch in tqdm(range(1, settings.epochs + 1), desc="perceive", disable=not progress):
        total = 0.0
        permutation = order.permutation(len(inputs))
        for start in range(0, len(inputs), settings.batch_size):
            rows = torch.from_numpy(permutation[start : start + settings.batch_size])
            loss = torch.nn.functional.mse_loss(predict(inputs[rows]), targets[rows])
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
            total += loss.item() * len(rows)
        with torch.no_grad():
            predicted = torch.cat(
                [
                    predict(torch.from_numpy(held_windows[start : start + 512]))
                    for start in range(0, len(held_windows), 512)
                ]
            ).numpy()
        history.append(
            PerceptionEpoch(epoch, total / len(inputs), errors(predicted * spread + mean))
        )
    return history
