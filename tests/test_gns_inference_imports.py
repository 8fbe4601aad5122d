"""Inference never imports training: loading and rolling out a model pulls in neither gns.train
nor what only training needs."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TRAINING = ("gns.train", "gns.fine_tune", "gns.weight_average")


@pytest.mark.parametrize("module", ["gns.api", "gns.evaluate", "gns.rollout_dataset", "gns"])
def test_an_inference_module_loads_no_training_module(module):
    code = f"import sys, {module}; print(' '.join(m for m in {TRAINING!r} if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert done.stdout.split() == []


def test_the_probe_sees_a_training_import():
    code = f"import sys, gns.train; print(' '.join(m for m in {TRAINING!r} if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert "gns.train" in done.stdout.split()
