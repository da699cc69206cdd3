"""The lab: diagnostics and research tools beside the product, installed as `qnav.lab`.

The product is what trains, evaluates, exports and runs a policy: simulate, train (paper and fast
presets), evaluate, export, run onboard, record, replay. The lab holds the tools that ask why a
policy does what it does: the oracle planner that knows the true future (`oracle`), the world
calibration table (`calibrate`), a run's diagnosis (`diagnose`), the controller in rooms that
are not the simulator's (`robustness`) and the shield's forecast against the truth
(`forecast_gauge`). What the lab tried and retired: docs/log/retired.md.

Nothing in the product imports the lab (tests/test_architecture.py checks it): the CLI shell
imports it inside the handlers of the lab's verbs.
"""
