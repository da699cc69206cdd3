"""The smallest training settings that still go through every stage of a run (rounds,
evaluations during training, the final test), for the tests that train: seconds each.
A test changes what it needs with `dataclasses.replace`."""

from dataclasses import replace

from qnav.training.config import FAST

TINY = replace(
    FAST,
    # Two rounds of 4 worlds, 30 steps at most; a small network learning from 8-sample batches.
    episodes=8, parallel_worlds=4, max_episode_steps=30, warmup_episodes=2, threads=1,
    hidden_size=8, batch_size=8, iterations_per_episode=1,
    # An evaluation of 2 episodes after each round, a 2-episode test.
    eval_every_episodes=4, eval_episodes=2, final_eval_episodes=2,
)  # fmt: skip
"""Two rounds of 4 worlds, an evaluation after each, a 2-episode test."""
