"""What judging doom can give a trained policy, measured on the states it drives into.

A doom judge (`contracts.judge_file`) is fitted to the planner's labels and keeps the policy's
action unless it judges it doomed; the controller's forecast shield instead takes the policy's
best-valued action among the least likely to collide. Before fitting a judge better, ask what a
perfect one would give: `audit` drives a run's greedy policy over evaluation layouts

- alone;
- judged by the exact doom labels (the judge rule: the policy's action unless every continuation
  collides, else the least colliding action), the ceiling of any judge fitted to them;
- shielded by the exact collision shares (the shield rule on the truth), the ceiling of a
  graded judgement;
- with the controller's look ahead on the onboard tracker: the forecast shield, and a doom judge
  file where one is given (`qnav.tracking.LookaheadAgent`, as the car runs them);

and labels every state each of them drives into with the planner's truth (`lab.oracle`), so
beside success it counts the decisive states (some action doomed, another not) met and the share
where the action taken, and where the policy's own choice, was safe. `qnav lab audit RUN`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.judge_file import judged_actions
from qnav.contracts.lookahead import shielded_actions
from qnav.controller.perception import TrackerSettings
from qnav.lab.decisive import is_decisive
from qnav.lab.oracle import collision_shares, doom_label_safety
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import Agent, EvalResult, EvalSettings, episode_outcomes
from qnav.sim.world import Observation, WorldState, take_rows
from qnav.tracking import LookaheadAgent, QAgent, lookahead_settings

Judgement = Literal["alone", "doom labels", "collision shares", "forecast", "judge file"]

JUDGEMENTS: tuple[Judgement, ...] = ("alone", "doom labels", "collision shares", "forecast")
"""What `audit` drives the policy with (and "judge file", where one is given)."""


class Audit(NamedTuple):
    """One judgement's drive of the policy over the layouts."""

    judgement: Judgement
    """Which (`JUDGEMENTS`, or "judge file")."""
    result: EvalResult
    """Outcomes of the episodes."""
    decisions: int
    """Decisions taken in them."""
    decisive: int
    """Of them, in decisive states (the planner's truth: some action doomed, another not)."""
    taken_safe: float
    """Share of the decisive states where the action taken was not doomed."""
    policy_safe: float
    """Share of them where the policy's own (greedy) action was not doomed."""
    overruled: float
    """Share of all decisions where the action taken was not the policy's."""

    @property
    def decisive_per_episode(self) -> float:
        """Decisive states met per episode: the policy's exposure, beside how it chose there."""
        return self.decisive / max(self.result.episodes, 1)


class _Labelled:
    """An agent acting for a greedy Q agent (the policy itself, or the look ahead around it),
    under an exact judgement where asked, with every decision's state labelled by the planner."""

    def __init__(
        self, agent: Agent, policy: QAgent, world: WorldConfig, judgement: Judgement
    ) -> None:
        self.agent, self.policy, self.world, self.judgement = agent, policy, world, judgement
        self._state: WorldState | None = None
        self._counting: NDArray[np.bool_] = np.zeros(0, dtype=bool)
        self.decisions = self.decisive = self.taken_safe = self.policy_safe = self.overruled = 0

    def watch(self, state: WorldState, counting: NDArray[np.bool_]) -> None:
        self._state, self._counting = state, counting.copy()

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.agent.start(worlds, episodes)

    def act(self, observation: Observation) -> NDArray[np.int64]:
        assert self._state is not None  # episode_outcomes shows the state before each decision
        counted = np.flatnonzero(self._counting)
        share = np.zeros((len(self._counting), NUM_ACTIONS))  # worlds done counting: never doomed
        share[counted] = collision_shares(self.world, take_rows(self._state, counted))
        taken = self.agent.act(observation)
        preferred = self.policy.last_q.argmax(axis=1)
        if self.judgement == "doom labels":
            taken = judged_actions(taken, doom_label_safety(share), 0.5)
        elif self.judgement == "collision shares":
            taken = shielded_actions(self.policy.last_q, share, 0.0)
        doomed = share == 1.0
        rows = np.flatnonzero(self._counting & is_decisive(doomed))  # the planner's truth
        self.decisions += int(self._counting.sum())
        self.decisive += rows.size
        self.taken_safe += int((~doomed[rows, taken[rows]]).sum())
        self.policy_safe += int((~doomed[rows, preferred[rows]]).sum())
        self.overruled += int((taken != preferred)[self._counting].sum())
        return taken


def audit(
    run_dir: Path,
    protocol: EvalSettings,
    judge_file: Path | None = None,
    progress: bool = False,
    judgements: tuple[Judgement, ...] = JUDGEMENTS,
) -> list[Audit]:
    """Drive the run's greedy policy over `protocol`'s layouts in its world under each of
    `judgements` (module docstring; "alone" by itself measures how many decisive states the
    policy drives into and how it chooses there), the same layouts for all. Every drive is set
    up before the first runs, so a judge file that is missing or judges another world is
    refused at once."""
    from qnav.training.agent import policy_agent
    from qnav.training.run_folder import load_network

    network, run = load_network(run_dir)
    world = run.world
    worlds = min(protocol.num_worlds, protocol.episodes)
    judged: tuple[Judgement, ...] = ("judge file",) if judge_file is not None else ()
    drives = []
    for judgement in judgements + judged:
        policy = policy_agent(network, world, worlds, run.train.window, seed=protocol.seed)
        agent: Agent = policy
        if judgement in ("forecast", "judge file"):
            mode = "shield" if judgement == "forecast" else "judge"
            agent = LookaheadAgent(
                policy,
                world,
                worlds,
                tracker=TrackerSettings(),
                lookahead=lookahead_settings(mode, judge_file if mode == "judge" else None),
                seed=protocol.seed,
            )
        drives.append(_Labelled(agent, policy, world, judgement))
    audits = []
    for labelled in tqdm(drives, desc="audit", disable=not progress):
        outcomes = episode_outcomes(world, labelled, protocol, watch=labelled.watch)
        decisive = max(labelled.decisive, 1)
        audits.append(
            Audit(
                judgement=labelled.judgement,
                result=EvalResult.of_outcomes(*outcomes),
                decisions=labelled.decisions,
                decisive=labelled.decisive,
                taken_safe=labelled.taken_safe / decisive,
                policy_safe=labelled.policy_safe / decisive,
                overruled=labelled.overruled / max(labelled.decisions, 1),
            )
        )
    return audits
