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
"$work/venv/bin/pip" install -q 'torch==2.13.0+cpu' -f https://download.pytorch.org/whl/torch/
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
"$work/venv/bin/python" -c "import gns; out = gns.load('real_cubes_16').rollout(shapes=['cube'], scales=2.0, \
positions=[[0, 0, 3]], quaternions=[[1, 0, 0, 0]], steps=3); assert out.positions.shape == (4, 1, 3)"
"$work/venv/bin/python" -m pipelines.movi_a --preset tiny --out movi_tiny --workers 1
test -s eval.json && test -s movi_tiny/report.md
# a recipe from the installed configs (stages and warm restarts), and the error breakdown of its model
"$work/venv/bin/python" -m pipelines.recipe tiny --out recipe_tiny --workers 1
grep -q "| default options |" recipe_tiny/report.md
"$work/venv/bin/python" -m pipelines.error_breakdown --run recipe_tiny/runs/b_2 --data recipe_tiny/data --json bd.json
test -s bd.json
# the zoo ships with its cards; a wrong name lists it
# written to a file first: `grep -q` stops reading at its match, and under pipefail the writer's
# broken pipe would fail the step whenever the listing is longer than the pipe takes at once
"$work/venv/bin/gns" models > models.txt && grep -q "^real_cubes_16$" models.txt
"$work/venv/bin/gns" models movi_a > card.txt && grep -q "pipelines.recipe movi_a" card.txt
if "$work/venv/bin/gns" models nope 2> err.txt; then exit 1; fi
grep -q "movi_a_fast" err.txt && test "$(wc -l < err.txt)" -eq 1
# the installed datagen re-simulates its own data exactly: the unperturbed row scores 0
"$work/venv/bin/python" -m pipelines.movi_a_sensitivity --data data --perturb exact:0 turn:1 --out sens
grep -q "^| exact (none) | 0.00 | 0.00 |" sens/report.md
# provenance from a wheel: versions and a fingerprint, no commit (no checkout around the code)
"$work/venv/bin/python" -c "import json; m = json.load(open('data/metadata.json')); p = m['provenance']; \
assert p['code'] is None and p['versions']['torch'] and len(m['fingerprint']) == 64, p"
"$work/venv/bin/gns" plot-curves run --out curves.png && test -s curves.png
# the extras are not installed here: using one is a one-line error naming it
if "$work/venv/bin/datagen" toss --out rayd --scenes 1 --backend ray --quiet 2> err.txt; then exit 1; fi
grep -q "rigid-gns\[ray\]" err.txt && test "$(wc -l < err.txt)" -eq 1
if "$work/venv/bin/gns" train --data data --out tb --config gns_tiny --tensorboard 2> err.txt; then exit 1; fi
grep -q "rigid-gns\[tensorboard\]" err.txt && test "$(wc -l < err.txt)" -eq 1
echo "wheel smoke test passed"
