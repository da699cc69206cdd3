"""The lab: diagnostics and research tools beside the product, installed as `qnav.lab`.

The product is what trains, evaluates, exports and runs a policy: simulate, train (paper and fast
presets), evaluate, export, run onboard, record, replay. The lab holds the tools that ask why a
policy does what it does: the oracle planner that knows the true future (`oracle`), the
decisive-state gauge built on it (`decisive`, `gauge`), the world calibration table
(`calibrate`), a run's diagnosis (`diagnose`) and the planner on the onboard tracker's estimate
(`tracking`). What the lab tried and retired: docs/log/retired.md.

Nothing in the product imports the lab (tests/test_architecture.py checks it): the CLI shell
imports it inside the handlers of the lab's verbs, and hands `qnav train` the decisive-state
gauge (`gauge.training_gauge`) as an opt-in extension of the training run.
"""
