#!/usr/bin/env bash
# CI: the package as a user installs it. Build a wheel, install it into a fresh venv (CPU torch
# first, as the README's set-up does) and, from a folder outside the checkout, generate, train
# and evaluate a tiny dataset with the installed commands and presets.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
python3 -m pip wheel --no-deps -q -w "$work/dist" "$repo"
python3 -m venv "$work/venv"
"$work/venv/bin/pip" install -q torch==2.13.0
"$work/venv/bin/pip" install -q "$work"/dist/*.whl
cd "$work"   # no checkout here: configs/ must come from the installed package
export OMP_NUM_THREADS=1
set -x
"$work/venv/bin/datagen" toss --out data --scenes 4 --valid 1 --test 2 --frames 8 --quiet
"$work/venv/bin/datagen" inspect data
"$work/venv/bin/gns" train --data data --out run --config gns_tiny --set train.steps=20 valid.every=0
"$work/venv/bin/gns" eval --run run --data data --json eval.json
# the Python API on the trained run (its checkpoint holds the meshes) and on a shipped model
"$work/venv/bin/python" -c "import gns; m = gns.load('run'); \
out = m.rollout(shapes=m.shapes[:1], positions=[[0, 0, 2]], quaternions=[[1, 0, 0, 0]], velocities=[[5, 0, 0]], \
friction=0.5, restitution=0.5, steps=3); assert out.positions.shape == (4, 1, 3)"
"$work/venv/bin/python" -c "import gns; out = gns.load('gns_real_cubes_n16').rollout(shapes=['cube'], scales=2.0, \
positions=[[0, 0, 3]], quaternions=[[1, 0, 0, 0]], steps=3); assert out.positions.shape == (4, 1, 3)"
"$work/venv/bin/python" -m pipelines.movi_a --preset tiny --out movi_tiny --workers 1
test -s eval.json && test -s movi_tiny/report.md
echo "wheel smoke test passed"
