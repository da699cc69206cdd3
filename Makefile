# Two commands do everything on a fresh machine with Python 3.11 and make:
#   make demo   set up .venv with what the demo needs ([train]) and run it (qnav/demo.py)
#   make test   set up .venv with the [dev] extra, lint, type-check and run the tests
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
# One stamp per install: [dev] (torch, the linters, mypy, SB3) for the tests and the tools below,
# the lighter [train] (torch, onnx, matplotlib) for the demo.
STAMP := $(VENV)/.installed
DEMO_STAMP := $(VENV)/.installed-demo

.PHONY: install demo test test-slow same-results test-stack test-sitl stack-sitl test-cluster bench-cluster fuzz playback-refs lint typecheck pytest docker-lint bench-sim bench-controller bench-bridge calibrate docs figures clean

# constraints.txt pins the versions a test's outcome depends on (every clone gets the same).
$(STAMP): pyproject.toml constraints.txt sim/_raycast.c
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@echo "installing qnav[dev] into $(VENV) (torch, onnx, ruff, mypy, SB3; minutes the first time)"
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[dev]'
	@touch $(STAMP)

$(DEMO_STAMP): pyproject.toml constraints.txt sim/_raycast.c
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@echo "installing qnav[train] into $(VENV) (torch, onnx, matplotlib; minutes the first time)"
	$(BIN)/python -m pip install --disable-pip-version-check --progress-bar on \
		-c constraints.txt -e '.[train]'
	@touch $(DEMO_STAMP)

install: $(STAMP)

demo: $(DEMO_STAMP)
	$(BIN)/python -m qnav.demo

test: lint typecheck docker-lint pytest

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# mypy over the package as installed (sim/ as qnav.sim, ...: pyproject's package-dir).
typecheck: $(STAMP)
	$(BIN)/python -m tests.typecheck qnav tests

docker-lint: $(STAMP)
	$(BIN)/hadolint --failure-threshold info Dockerfile

pytest: $(STAMP)
	$(BIN)/pytest

# Long checks (many-episode evaluations, training runs): not part of `make test`.
test-slow: $(STAMP)
	$(BIN)/pytest -m slow

# Studies on Ray (docs/cluster.md): installs the [cluster] extra into .venv, then a local
# instance with two workers, a worker killed mid-run, and a two-node cluster on this machine.
test-cluster: $(STAMP)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[dev,cluster]'
	$(BIN)/pytest -m cluster tests/training/test_cluster_ray.py -p no:cacheprovider -rs

# A small fixed study on 1 Ray worker, then on 2: the wall times and their ratio (docs/cluster.md).
bench-cluster: $(STAMP)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[dev,cluster]'
	$(BIN)/qnav bench cluster

# Malformed payloads against the real controller and bridge processes (issue 18 part 7):
# 10,000 per controller key, 2,000 per bridge key; `make test` runs a 150-per-key slice.
fuzz: $(STAMP)
	QNAV_FUZZ_PAYLOADS=10000 QNAV_FUZZ_BRIDGE_PAYLOADS=2000 $(BIN)/pytest tests/fuzz -s -p no:cacheprovider -o addopts="" --timeout 3600

# The full stack (sim-car, controller, bridge, recorder as processes) against in-process eval.
test-stack: $(STAMP)
	$(BIN)/pytest -m stack -s

# The bridge against ArduPilot Rover SITL (docs/bridge-testing.md, "ArduPilot in the loop"): set
# ARDUPILOT_SITL to an ardurover binary (never vendored; the docs say how to build one). It runs
# in a network namespace of its own where unshare allows (loopback only: the autopilot's ports
# are reachable from nowhere else); without ARDUPILOT_SITL every test is skipped and says why.
SITL_NETNS := $(shell unshare --net true 2>/dev/null && echo "unshare --net" || \
	(unshare --net --map-root-user true 2>/dev/null && echo "unshare --net --map-root-user"))
# SITL_TESTS: what pytest collects (e.g. tests/sitl/trace_stops.py, a trace not in the suite).
SITL_TESTS ?= tests/sitl
test-sitl: $(STAMP)
	$(SITL_NETNS) sh -c '$(if $(SITL_NETNS),ip link set lo up && )$(BIN)/pytest -m sitl $(SITL_TESTS) -p no:cacheprovider -rs $(SITL_ARGS)'

# The full stack on the firmware: policy -> controller -> bridge -> ArduPilot Rover SITL, the
# pose from the autopilot, walls and lidar simulated around it; beside the same episodes in
# process (docs/bridge-testing.md, "The full stack on the firmware"). Loopback-only namespace as above.
STACK_POLICY ?= tests/data/stack/policy.onnx
STACK_EPISODES ?= 20
stack-sitl: $(STAMP)
	$(SITL_NETNS) sh -c '$(if $(SITL_NETNS),ip link set lo up && )$(BIN)/python -m qnav stack --vehicle sitl --policy $(STACK_POLICY) --episodes $(STACK_EPISODES) --no-record --out out/stack-sitl $(STACK_ARGS)'

# Regenerate the playback tests' reference decisions on purpose, and show what changed
# (tests/data/make_playback_data.py --refs, docs/recordings.md; the bridge's:
# tests/data/make_bridge_playback.py --refs, docs/bridge-testing.md). Commit the new references.
# Does the working tree train and evaluate bit for bit as commit REF does? (refactors: IDENTICAL)
same-results: $(STAMP)
	bash tests/same_results/run.sh $(or $(REF),HEAD)

playback-refs: $(STAMP)
	$(BIN)/python tests/data/make_playback_data.py --refs
	$(BIN)/python tests/data/make_bridge_playback.py --refs
	git diff --stat -- tests/data/playback tests/data/bridge_playback

bench-sim: $(STAMP)
	$(BIN)/qnav bench sim

# End-to-end latency of the controller daemon (three processes on loopback, 5 Hz and 50 Hz scans).
bench-controller: $(STAMP)
	$(BIN)/qnav bench controller

# Command on zenoh to MAVLink on the wire (p50, p99), and the failsafe stop's delay.
bench-bridge: $(STAMP)
	$(BIN)/qnav bench bridge --baseline

calibrate: $(STAMP)
	$(BIN)/qnav lab calibrate

# The paper's figures 3 (action maps early and late) and 10 (trajectories, the lidar-less toy car
# too) into docs/img: two short trainings with snapshots, about 15 minutes on 2 cores.
FIGURE_RUNS := runs/figures
figures: $(STAMP)
	$(BIN)/qnav train --scenario walls-increment --seed 0 --episodes 120 \
		--train-set train.snapshot_every_episodes=8 --run-dir $(FIGURE_RUNS)/walls-increment
	$(BIN)/qnav figures $(FIGURE_RUNS)/walls-increment --out docs/img
	$(BIN)/qnav train --scenario toycar-inertia --seed 0 --episodes 200 \
		--train-set train.snapshot_every_episodes=8 --run-dir $(FIGURE_RUNS)/toycar-inertia
	$(BIN)/qnav figures $(FIGURE_RUNS)/toycar-inertia --out docs/img

# Regenerate the settings reference from the settings classes.
docs: $(STAMP)
	$(BIN)/qnav scenarios --reference > docs/settings.md

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache out
