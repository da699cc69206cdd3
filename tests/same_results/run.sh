#!/usr/bin/env bash
# `make same-results REF=COMMIT`: do the code at COMMIT and the working tree train and evaluate
# bit for bit alike? Short seeded runs of both presets, a walls and an obstacle world, n-step
# and hindsight targets, from each tree's own code (`python -m` puts the working folder, the
# tree's view below, first on sys.path, ahead of the editable install), digested without
# timings (digest.py) and compared. A refactor must print IDENTICAL; a change of behaviour prints where
# the digests differ. About 5 minutes on 2 cores.
set -euo pipefail
ref=${1:?usage: run.sh COMMIT}
here=$(git rev-parse --show-toplevel)
py=${PYTHON:-$here/.venv/bin/python}
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
mkdir -p "$scratch/ref"
git -C "$here" archive "$ref" | tar -x -C "$scratch/ref"

common=(--quiet --train-set train.hidden_size=16 --train-set train.iterations_per_episode=2
  --train-set train.batch_size=16 --train-set train.eval_every_episodes=4
  --train-set train.eval_episodes=4 --train-set train.final_eval_episodes=4
  --train-set train.max_episode_steps=30 --train-set train.warmup_episodes=2
  --train-set train.threads=1)

# A tree's own package: its qnav/ with its folders linked in as pyproject's package-dir maps them
# (in scratch; a tree of before that change links them itself), run from there.
view() {  # view SOURCE_TREE VIEW_DIR
  local src=$1 at=$2 part
  mkdir -p "$at" && cp -RP "$src/qnav" "$at/qnav"
  for part in contracts controller firmware_bridge lab sim simcar training; do
    rm -f "$at/qnav/$part" && ln -s "$src/$part" "$at/qnav/$part"
  done
}

runs() {  # runs SOURCE_TREE OUT_DIR
  local src=$1 out=$2
  local -a common=("${common[@]}")
  # A tree from before the decisive-state gauge was retired (issue 54) has it: off there.
  if grep -q gauge_episodes "$src/training/config.py"; then
    common+=(--train-set train.gauge_episodes=0)
  fi
  mkdir -p "$out"
  view "$src" "$out.view"
  (
    cd "$out.view"
    "$py" -m qnav train --scenario walls-increment --preset paper --seed 3 --episodes 6 \
      --run-dir "$out/walls-paper" "${common[@]}" --train-set train.target_update_period=5 \
      --train-set train.snapshot_every_episodes=3
    "$py" -m qnav train --scenario walls-increment --preset fast --seed 1 --episodes 12 \
      --run-dir "$out/walls-fast" "${common[@]}" --train-set train.parallel_worlds=4
    "$py" -m qnav train --scenario obstacles-increment --preset fast --seed 2 --episodes 12 \
      --run-dir "$out/obstacles-fast" "${common[@]}" --train-set train.parallel_worlds=4
    "$py" -m qnav train --scenario obstacles-increment --preset paper --seed 0 --episodes 6 \
      --model feedforward --relabel hindsight --run-dir "$out/obstacles-paper-hindsight" \
      "${common[@]}" --train-set train.target_update_period=4
    "$py" -m qnav train --scenario obstacles-increment --preset fast --seed 4 --episodes 8 \
      --run-dir "$out/obstacles-fast-nstep3" "${common[@]}" --train-set train.parallel_worlds=4 \
      --train-set train.n_step=3
    "$py" -m qnav eval --policy "$out/obstacles-fast" --episodes 5 --json > "$out/eval-obstacles-fast.json"
    "$py" -m qnav eval --policy "$out/walls-paper" --episodes 5 --json > "$out/eval-walls-paper.json"
  )
}

echo "runs at $ref ..."; runs "$scratch/ref" "$scratch/before"
echo "runs in the working tree ..."; runs "$here" "$scratch/after"
"$py" "$here/tests/same_results/digest.py" "$scratch/before" > "$scratch/before.json"
"$py" "$here/tests/same_results/digest.py" "$scratch/after" > "$scratch/after.json"
if cmp -s "$scratch/before.json" "$scratch/after.json"; then
  echo "IDENTICAL: the working tree trains and evaluates as $ref does"
else
  diff "$scratch/before.json" "$scratch/after.json" | head -40
  echo "DIFFERENT from $ref (first differing lines above)"
  exit 1
fi
