"""Labels spent where the doom network doubts: rounds of drive, choose, label, refit.

The probe (`lab.probe`) shows what a doom judgement is worth: exact doom labels lift the blind
go-to-target controller past the paper's Table I as a shield, and a fitted network gets there
only as far as its labelled decisive states take it. Labels are dear (the planner's rollouts,
about 4 ms a state) and decisive states rare (3 % of driven ones), while driving is nearly free.
So each round drives many fresh layouts with go-to-target shielded by the latest fit (the
states the judgement being improved leads the robot into, as DAgger labels where the learner
goes), asks the fit how sure it is of each action in every visited state, labels only the most
doubtful share (where three quarters of the decisive states are), refits on everything labelled
so far, and measures the fit twice: on the gauge's held-out decisive states and as a shield on
the test protocol.

With `probe.redrawn_from = RUN` nobody drives: round 0 is the probe's re-drawn set (RUN's own
stored steps among fresh obstacles, `lab.redrawn`), and each round draws as many fresh
re-drawn states at RUN's stored steps and labels the most doubtful share of them, so every label
stays within the episodes RUN collected.

Rounds are kept in a folder, one file each, written atomically: a killed run loses at most
the round under way, and rerunning the command (with more `--rounds`) resumes after the last
finished one, so rounds add up across sessions. `qnav lab label` runs it. A diagnostic, like
the probe: nothing in training or the product imports it.
"""

from __future__ import annotations

import csv
import difflib
import io
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, NamedTuple, get_type_hints

import numpy as np
import torch
from numpy.typing import NDArray
from tqdm import tqdm

from qnav.contracts.errors import ConfigError
from qnav.contracts.judge_file import judge_inputs, judged_actions
from qnav.contracts.settings import check_range, to_toml
from qnav.lab.decisive import (
    DecisiveStates,
    GaugeSettings,
    cached,
    is_decisive,
    load_with_world,
    save_with_world,
    score,
)
from qnav.lab.oracle import collision_shares
from qnav.lab.probe import (
    ProbeSettings,
    SafeProbability,
    decisive_only,
    doom_network,
    fit_doom,
    judged_safe,
    labelled_features,
    labelled_states,
    network_safety,
    shielded_go_to_target,
    state_features,
    state_inputs,
    tracked_safety,
)
from qnav.lab.redrawn import (
    LABEL_BATCH,
    StoredSteps,
    encoded_view,
    redrawn_worlds,
    stored_steps,
)
from qnav.sim import paper
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, drive, go_to_target
from qnav.sim.world import Observation, WorldState, concatenate_rows, take_rows

LABEL_PROBE = ProbeSettings(inputs="slots", epochs=40, episodes_per_driver=1200)
"""The fit `qnav lab label` starts from and refits each round: the obstacle-slot network on the
probe's 1200-episode labelled set, 40 passes (the probe's best measured fit)."""


@dataclass(frozen=True)
class DoubtSettings:
    """Each round's drive, choice of states to label, and measurement."""

    SECTION = "doubt"

    driver: Literal["shielded", "go-to-target"] = "shielded"
    """Who drives each round's episodes: go-to-target shielded by the latest fit (labels where
    the judgement being improved takes the robot, as DAgger does), or go-to-target alone. With
    `probe.redrawn_from` nobody drives, and the drive's settings below play no part."""
    episodes_per_round: int = 6000
    """Episodes driven each round (fresh layouts every round)."""
    labelled_share: float = 0.2
    """Share of each round's visited states labelled by the planner: the most doubtful ones."""
    ordinary_share: float = 0.3
    """Share of a round's labelled states that are not decisive kept in the fit beside every
    decisive one (as the probe's labelled set keeps)."""
    max_episode_steps: int = 200
    """Steps of each driven episode at most (the training episodes' length)."""
    num_worlds: int = 1000
    """Episodes driven (and labelled) together."""
    seed: int = 5151
    """Seed of the driven layouts (apart from training's, the gauge's, the probe's and the
    test's)."""
    shield_episodes: int = 1000
    """Test-protocol episodes of go-to-target shielded by each round's fit (0: gauge only)."""

    def __post_init__(self) -> None:
        check_range(self, "episodes_per_round", self.episodes_per_round, 1, 10**8)
        check_range(self, "labelled_share", self.labelled_share, 0.0, 1.0, exclusive_low=True)
        check_range(self, "ordinary_share", self.ordinary_share, 0.0, 1.0)
        check_range(self, "max_episode_steps", self.max_episode_steps, 1, 10**7)
        check_range(self, "num_worlds", self.num_worlds, 1, 10**6)
        check_range(self, "shield_episodes", self.shield_episodes, 0, 10**7)


class LabelledRound(NamedTuple):
    """The states one round labelled, with what a doom network sees there."""

    world: WorldState
    """The true state of each labelled world (K rows)."""
    context: NDArray[np.float32]
    """(K, 5) the slot network's context (`contracts.judge_file.judge_inputs`)."""
    slots: NDArray[np.float32]
    """(K, OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES) the obstacles' slots."""
    collide_share: NDArray[np.float64]
    """(K, A) the share of the planner's continuations after each first action that collide."""
    visited: int
    """States visited in the round, labelled or not."""

    def save(self, path: Path) -> None:
        """Write to an .npz file atomically (a killed run leaves the old file or the new one)."""
        save_with_world(path, self._asdict())

    @classmethod
    def load(cls, path: Path) -> LabelledRound:
        """Read what `save` wrote."""
        fields = load_with_world(path)
        return cls(**{**fields, "visited": int(fields["visited"])})


class RoundReport(NamedTuple):
    """One row of the folder's progress.csv: the labels so far and the fit on them."""

    round: int
    """0: the probe's labelled set alone; then each doubt-led round."""
    visited: int
    """States visited in this round's drive."""
    labelled: int
    """States the planner labelled in this round."""
    labelled_decisive: int
    """Decisive states among them."""
    fitted_states: int
    """States the fit after this round saw (all rounds so far)."""
    fitted_decisive: int
    """Decisive states among them."""
    gauge_safe: float
    """Share of the gauge's held-out decisive states where the fit's safest action is safe."""
    gauge_balanced: float
    """The same averaged over doom patterns (1/2 for any choice blind to the obstacles)."""
    shield_success: float
    """Success of go-to-target shielded by the fit on the test protocol (nan: not measured)."""
    shield_collision: float
    """Its collision share."""
    overruled: float
    """Share of the shielded decisions that overruled go-to-target."""
    minutes: float
    """Wall-clock minutes of the round (drive, label, fit, measure)."""


def doubt(safe_probability: NDArray[np.floating]) -> NDArray[np.floating]:
    """(N,) how unsure a judgement (N, A) is in each state: the distance of its least certain
    action's probability of being safe from 1/2, so smaller is more doubtful."""
    return np.asarray(np.abs(safe_probability - 0.5).min(axis=1))


def most_doubtful(safe_probability: NDArray[np.floating], share: float) -> NDArray[np.intp]:
    """Indices of the most doubtful `share` of the states (at least one where there are any)."""
    count = max(1, round(share * len(safe_probability))) if len(safe_probability) else 0
    return np.argsort(doubt(safe_probability), kind="stable")[:count]


def drive_and_label(
    world: WorldConfig,
    safety: SafeProbability,
    settings: DoubtSettings,
    round_index: int,
    progress: bool = False,
) -> LabelledRound:
    """Round `round_index` (1-based): drive its fresh layouts (`DoubtSettings.driver`), keep the
    most doubtful share of each batch of worlds' visited states, and label those with the
    planner."""
    config = replace(world, max_episode_steps=settings.max_episode_steps)
    first = (round_index - 1) * settings.episodes_per_round
    batches = [
        np.arange(start, min(start + settings.num_worlds, first + settings.episodes_per_round))
        for start in range(first, first + settings.episodes_per_round, settings.num_worlds)
    ]
    return _joined(
        [
            _label_batch(world, config, safety, settings, episodes)
            for episodes in tqdm(
                batches, desc=f"round {round_index}", unit="batch", disable=not progress
            )
        ]
    )


def redraw_and_label(
    world: WorldConfig,
    steps: StoredSteps,
    network: torch.nn.Module,
    probe: ProbeSettings,
    settings: DoubtSettings,
    *,
    round_index: int,
    window: int,
    progress: bool = False,
) -> LabelledRound:
    """Round `round_index` (1-based) among re-drawn obstacles: `probe.redrawn_states` of a
    run's stored `steps`, drawn uniformly, each among fresh obstacles that kept clear of the
    robot over its last `window` frames; the most doubtful share of each batch is labelled by
    the planner. No episode is driven."""
    chance = np.random.default_rng([settings.seed, round_index])
    picked = chance.integers(0, len(steps.pose), probe.redrawn_states)
    parts = []
    for start in tqdm(
        range(0, picked.size, LABEL_BATCH),
        desc=f"round {round_index}",
        unit="batch",
        disable=not progress,
    ):
        rows = picked[start : start + LABEL_BATCH]
        state = redrawn_worlds(world, steps, rows, window=window, seed=settings.seed, chance=chance)
        context, slots = judge_inputs(state.velocity, *encoded_view(world, state))
        features: tuple[NDArray[np.float32], ...] = (context, slots)
        if probe.inputs == "state":
            features = state_features(state, world.arena.size_m)
        pick = most_doubtful(judged_safe(network, features), settings.labelled_share)
        chosen = take_rows(state, pick)
        parts.append(
            LabelledRound(
                world=chosen,
                context=context[pick],
                slots=slots[pick],
                collide_share=collision_shares(world, chosen),
                visited=rows.size,
            )
        )
    return _joined(parts)


def _joined(parts: list[LabelledRound]) -> LabelledRound:
    """One round from the rounds of its batches."""
    return LabelledRound(
        world=concatenate_rows([part.world for part in parts]),
        context=np.concatenate([part.context for part in parts]),
        slots=np.concatenate([part.slots for part in parts]),
        collide_share=np.concatenate([part.collide_share for part in parts]),
        visited=sum(part.visited for part in parts),
    )


def _label_batch(
    world: WorldConfig,
    config: WorldConfig,
    safety: SafeProbability,
    settings: DoubtSettings,
    episodes: NDArray[np.int64],
) -> LabelledRound:
    """One batch of worlds driven together (`config`: the world with the round's episode
    length), its most doubtful states labelled."""
    states: list[WorldState] = []
    inputs: list[tuple[NDArray[np.float32], ...]] = []
    judged: list[NDArray[np.floating]] = []

    def act(state: WorldState, observation: Observation) -> NDArray[np.int64]:
        states.append(state)
        inputs.append(state_inputs(world, "slots", state, observation))
        judged.append(safety(state, observation))
        preferred = go_to_target(observation.target_features())
        if settings.driver == "go-to-target":
            return preferred
        return judged_actions(preferred, judged[-1], 0.5)

    drive(config, settings.seed, episodes, act)
    visited = concatenate_rows(states)
    pick = most_doubtful(np.concatenate(judged), settings.labelled_share)
    chosen = take_rows(visited, pick)
    return LabelledRound(
        world=chosen,
        context=np.concatenate([context for context, _ in inputs])[pick],
        slots=np.concatenate([slots for _, slots in inputs])[pick],
        collide_share=collision_shares(world, chosen),
        visited=len(visited.steps),
    )


class TrainingSet(NamedTuple):
    """Everything labelled so far, as the fit sees it."""

    inputs: tuple[torch.Tensor, ...]
    """The network's inputs per state."""
    collide_share: NDArray[np.floating]
    """(K, A) their labels."""


def training_set(
    world: WorldConfig,
    base: DecisiveStates,
    probe: ProbeSettings,
    settings: DoubtSettings,
    rounds: list[LabelledRound],
) -> TrainingSet:
    """The probe's labelled set `base` and, from each round, its decisive states and a seeded
    `ordinary_share` of the others."""
    parts = [labelled_features(world, probe.inputs, base)]
    shares: list[NDArray[np.floating]] = [base.collide_share]
    for index, labelled in enumerate(rounds, start=1):
        decisive = is_decisive(labelled.collide_share == 1.0)
        draw = np.random.default_rng([settings.seed, index]).random(len(decisive))
        keep = decisive | (draw < settings.ordinary_share)
        parts.append(
            state_features(take_rows(labelled.world, np.flatnonzero(keep)), world.arena.size_m)
            if probe.inputs == "state"
            else (labelled.context[keep], labelled.slots[keep])
        )
        shares.append(labelled.collide_share[keep])
    inputs = tuple(torch.from_numpy(np.concatenate([part[i] for part in parts])) for i in range(2))
    return TrainingSet(inputs, np.concatenate(shares))


class LabelFolder:
    """A folder of rounds: settings.toml (what the rounds were made with), round-NNN.npz (each
    round's labels), network.pt (the latest fit), progress.csv (a `RoundReport` per round) and
    progress.png (success and gauge against labelled decisive states)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def claim(self, settings_text: str) -> None:
        """Make the folder, or check that its rounds were made with the same settings (resuming
        with others would mix labels of different worlds or choices)."""
        written = self.path / "settings.toml"
        if written.exists():
            before, now = _setting_lines(written.read_text()), _setting_lines(settings_text)
            if before != now:
                changed = [line[2:] for line in difflib.ndiff(before, now) if line.startswith("+ ")]
                raise ConfigError(
                    f"{self.path} holds rounds made with other settings ({written}); these "
                    f"differ: {', '.join(changed) or 'settings removed'}. Resume with the same "
                    "settings or use a new folder"
                )
            return
        self.path.mkdir(parents=True, exist_ok=True)
        _write_atomically(written, settings_text)

    def round_path(self, index: int) -> Path:
        return self.path / f"round-{index:03d}.npz"

    def rounds(self) -> Iterator[LabelledRound]:
        """The finished rounds, in order (a gap ends them)."""
        index = 1
        while self.round_path(index).exists():
            yield LabelledRound.load(self.round_path(index))
            index += 1

    def reports(self) -> list[RoundReport]:
        """The progress.csv rows written so far."""
        path = self.path / "progress.csv"
        if not path.exists():
            return []
        with path.open() as file:
            kinds = get_type_hints(RoundReport)  # each column read back as its field's type
            return [
                RoundReport._make(kinds[name](row[name]) for name in RoundReport._fields)
                for row in csv.DictReader(file)
            ]

    def write_reports(self, reports: list[RoundReport]) -> None:
        """Write progress.csv afresh, atomically (a killed run leaves whole rows only)."""
        text = io.StringIO()
        writer = csv.writer(text)
        writer.writerow(RoundReport._fields)
        writer.writerows(reports)
        _write_atomically(self.path / "progress.csv", text.getvalue())


def _base_set(
    world: WorldConfig,
    store: LabelFolder,
    probe: ProbeSettings,
    gauge: GaugeSettings,
    progress: bool,
) -> DecisiveStates:
    """Round 0's labels: the probe's driven set (from the cache), or with `probe.redrawn_from`
    its re-drawn set, labelled once and kept in the folder (round-000.npz: minutes of labels)."""
    path = store.round_path(0)
    if probe.redrawn_from and path.exists():
        return DecisiveStates.load(path)
    base = labelled_states(world, probe, gauge, progress)
    if probe.redrawn_from:
        base.save(path)
    return base


def _setting_lines(toml: str) -> list[str]:
    """The settings of a TOML text, without its comments (which explain, and may be reworded)."""
    return [line for line in toml.splitlines() if line.strip() and not line.startswith("#")]


def _write_atomically(path: Path, text: str) -> None:
    partial = path.with_suffix(path.suffix + ".partial")
    partial.write_text(text)
    partial.replace(path)


def run_rounds(
    world: WorldConfig,
    folder: Path,
    rounds: int,
    *,
    probe: ProbeSettings = LABEL_PROBE,
    settings: DoubtSettings = DoubtSettings(),
    gauge: GaugeSettings | None = None,
    progress: bool = False,
) -> Iterator[RoundReport]:
    """Bring `folder` to `rounds` doubt-led rounds (resuming after its last finished one), each
    refitted and measured; yields the report of every round, those already in the folder first,
    round 0 being the fit on the probe's labelled set alone (`gauge`: the held-out decisive
    states, whose episode length and window the labelled set shares)."""
    if probe.inputs == "lidar":
        raise ConfigError(
            "qnav lab label needs probe.inputs = state or slots: the rounds judge each driven "
            "state from the world, without a window of scans"
        )
    if probe.labelled_actions == "taken":
        raise ConfigError(
            "qnav lab label needs probe.labelled_actions = all or random: its rounds record no "
            "driver's action"
        )
    if not world.obstacles.count:
        raise ConfigError(f"scenario {world.name!r} has no moving obstacles: nothing is doomed")
    gauge = gauge or GaugeSettings()
    store = LabelFolder(folder)
    store.claim(
        to_toml(world, "world")
        + to_toml(probe, probe.SECTION)
        + to_toml(settings, settings.SECTION)
        + to_toml(gauge, gauge.SECTION)
    )
    return _rounds(
        world, store, rounds, probe=probe, settings=settings, gauge=gauge, progress=progress
    )


def _rounds(
    world: WorldConfig,
    store: LabelFolder,
    rounds: int,
    *,
    probe: ProbeSettings,
    settings: DoubtSettings,
    gauge: GaugeSettings,
    progress: bool,
) -> Iterator[RoundReport]:
    folder = store.path
    torch.set_num_threads(probe.threads)
    held_out = decisive_only(cached(world, gauge, progress))
    protocol = EvalSettings(episodes=settings.shield_episodes)
    blind = (
        shielded_go_to_target(world, None, protocol)[0].success if protocol.episodes else math.nan
    )
    labelled = list(store.rounds())
    reports = store.reports()[: len(labelled) + 1]
    yield from reports
    # Read (or label) only when a round needs them: a finished folder, rerun for its final
    # test, reads neither.
    base: DecisiveStates | None = None
    stored: StoredSteps | None = None
    network = doom_network(world, probe.inputs)
    fitted_path = folder / "network.pt"
    for index in range(len(labelled), rounds + 1):
        started = time.monotonic()
        if index > len(labelled):
            if probe.redrawn_from:
                if stored is None:
                    stored = stored_steps(world, Path(probe.redrawn_from), gauge.window)
                fresh = redraw_and_label(
                    world,
                    stored,
                    network,
                    probe,
                    settings,
                    round_index=index,
                    window=gauge.window,
                    progress=progress,
                )
            else:
                fresh = drive_and_label(
                    world, network_safety(world, network, probe.inputs), settings, index, progress
                )
            fresh.save(store.round_path(index))
            labelled.append(fresh)
        if index < len(reports) and fitted_path.exists():
            network.load_state_dict(torch.load(fitted_path))
            network.eval()
            continue
        if base is None:  # round 0's minutes include labelling its set
            base = _base_set(world, store, probe, gauge, progress)
        data = training_set(world, base, probe, settings, labelled)
        torch.manual_seed(probe.seed)
        network = doom_network(world, probe.inputs)
        fit_doom(network, data.inputs, data.collide_share, probe, progress=progress)
        torch.save(network.state_dict(), fitted_path.with_suffix(".partial"))
        fitted_path.with_suffix(".partial").replace(fitted_path)
        report = _measure(
            world,
            network,
            probe=probe,
            held_out=held_out,
            protocol=protocol,
            fresh=labelled[index - 1] if index else None,
            base=base,
            data=data,
        )
        report = report._replace(round=index, minutes=(time.monotonic() - started) / 60)
        del reports[index:]  # a report whose fit was lost is replaced, not repeated
        reports.append(report)
        store.write_reports(reports)
        plot_progress(reports, folder / "progress.png", world.name, blind)
        yield report


TRACKER_TEST_NOISE_M = 0.02
"""Range noise of the final test's noisy scans (a hobby lidar's, as the tracker's own check)."""

THRESHOLDS = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.98)
"""The shield's thresholds the final test chooses among: go-to-target's action is kept where the
fit's P(safe) exceeds it. A miss (keeping a doomed action) ends the episode, a false alarm costs
a detour, so a good enough fit wants a threshold above 1/2; how far depends on the fit (the fits
of re-drawn rounds chose 0.9 when it was the highest offered)."""


class FinalTest(NamedTuple):
    """The folder's latest fit shielding go-to-target at a threshold chosen on validation
    layouts, on the test protocol from the truth and from the tracker."""

    validation: dict[float, float]
    """Success on the validation layouts at each of `THRESHOLDS`."""
    threshold: float
    """The best of them there."""
    half: EvalResult
    """Test protocol, threshold 1/2, the fit seeing the world's truth (as the rounds measure)."""
    truth: EvalResult
    """Test protocol at the chosen threshold, from the world's truth."""
    tracked: EvalResult
    """The same from the onboard tracker's estimate on exact scans (`lab.probe.tracked_safety`)."""
    tracked_noisy: EvalResult
    """The same with `TRACKER_TEST_NOISE_M` of range noise on the scans."""


def fitted_network(world: WorldConfig, folder: Path, probe: ProbeSettings) -> torch.nn.Module:
    """The folder's latest fit (network.pt), in eval mode, on what a car perceives."""
    if probe.inputs != "slots":
        raise ConfigError(
            "a fit a car can ask needs probe.inputs = slots (the state is not perceived)"
        )
    fitted_path = folder / "network.pt"
    if not fitted_path.exists():
        raise ConfigError(f"{folder} holds no fit yet ({fitted_path}): run a round first")
    network = doom_network(world, probe.inputs)
    network.load_state_dict(torch.load(fitted_path))
    return network.eval()


def final_test(
    world: WorldConfig,
    folder: Path,
    probe: ProbeSettings,
    settings: DoubtSettings,
    episodes: int,
) -> FinalTest:
    """Go-to-target shielded by the folder's latest fit: the threshold chosen on `episodes`
    validation layouts (seed `settings.seed + 1`, apart from the rounds' and the test's), then
    the first `episodes` test-protocol layouts at it, the fit seeing the world's truth, the
    onboard tracker's estimate (as the car's controller would), and that with noisy scans."""
    network = fitted_network(world, folder, probe)
    truth = network_safety(world, network, "slots")
    validation_layouts = EvalSettings(episodes=episodes, seed=settings.seed + 1)
    validation = {
        threshold: shielded_go_to_target(world, truth, validation_layouts, threshold)[0].success
        for threshold in THRESHOLDS
    }
    threshold = max(THRESHOLDS, key=lambda t: validation[t])
    protocol = EvalSettings(episodes=episodes)

    def test(safety: SafeProbability, at: float) -> EvalResult:
        return shielded_go_to_target(world, safety, protocol, at)[0]

    return FinalTest(
        validation=validation,
        threshold=threshold,
        half=test(truth, 0.5),
        truth=test(truth, threshold),
        tracked=test(tracked_safety(world, network), threshold),
        tracked_noisy=test(
            tracked_safety(world, network, range_noise_m=TRACKER_TEST_NOISE_M), threshold
        ),
    )


def _measure(
    world: WorldConfig,
    network: torch.nn.Module,
    *,
    probe: ProbeSettings,
    held_out: DecisiveStates,
    protocol: EvalSettings,
    fresh: LabelledRound | None,
    base: DecisiveStates,
    data: TrainingSet,
) -> RoundReport:
    """The fit's gauge and shielded success, with the round's sizes (minutes left 0); for
    round 0 (`fresh` None) the sizes of the probe's labelled set `base`, every visited state of
    which was labelled."""
    safest = judged_safe(network, labelled_features(world, probe.inputs, held_out)).argmax(axis=1)
    judged = score(held_out, safest)
    if fresh is None:
        visited = labelled = int(base.visited.sum())
        labelled_decisive = int(is_decisive(base.doomed).sum())
    else:
        visited, labelled = fresh.visited, len(fresh.collide_share)
        labelled_decisive = int(is_decisive(fresh.collide_share == 1.0).sum())
    shielded: EvalResult | None = None
    overruled = math.nan
    if protocol.episodes:
        shielded, overruled = shielded_go_to_target(
            world, network_safety(world, network, probe.inputs), protocol
        )
    return RoundReport(
        round=0,
        visited=visited,
        labelled=labelled,
        labelled_decisive=labelled_decisive,
        fitted_states=len(data.collide_share),
        fitted_decisive=int(is_decisive(data.collide_share == 1.0).sum()),
        gauge_safe=judged.safe,
        gauge_balanced=judged.balanced,
        shield_success=shielded.success if shielded else math.nan,
        shield_collision=shielded.collision if shielded else math.nan,
        overruled=overruled,
        minutes=0.0,
    )


def plot_progress(
    reports: list[RoundReport], path: Path, world: str, blind_success: float = math.nan
) -> Path:
    """Shielded success and the gauge against the labelled decisive states fitted to, beside
    go-to-target alone (`blind_success`, where measured) and the paper's recurrent mean for the
    scenario where it has one."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(6.4, 6.0), dpi=100)
    FigureCanvasAgg(figure)
    success, gauge = figure.subplots(2, 1, sharex=True)
    decisive = [report.fitted_decisive for report in reports]
    success.plot(
        decisive,
        [report.shield_success for report in reports],
        marker="o",
        label="go-to-target shielded by the fit",
    )
    if not math.isnan(blind_success):
        success.axhline(
            blind_success, color="0.5", linestyle=":", label=f"go-to-target alone ({blind_success})"
        )
    if world in paper.RECURRENT:
        mean = paper.RECURRENT[world][0].success
        success.axhline(mean, color="tab:red", linestyle="--", label=f"paper, recurrent ({mean})")
    success.set_ylabel("test success")
    success.legend(loc="best", fontsize="small")
    success.grid(alpha=0.3)
    success.set_title(f"{world}: labels spent where the doom network doubts")
    gauge.plot(decisive, [report.gauge_balanced for report in reports], marker="o")
    gauge.set_ylabel("gauge, balanced")
    gauge.set_xlabel("labelled decisive states fitted to (round 0: the probe's set)")
    gauge.set_xscale("log", base=2)
    gauge.grid(alpha=0.3)
    figure.tight_layout()
    partial = path.with_suffix(".partial.png")
    figure.savefig(partial)
    partial.replace(path)
    return path
