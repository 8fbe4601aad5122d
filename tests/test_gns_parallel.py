"""Training on several processes (torchrun, gloo on the CPU) against one process, same global batch."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from gns_fixtures import write_toss_dataset

from datagen.cli import main as datagen_main
from gns.processes import share, windows
from gns.run_folder import World
from gns.config import build_config
from gns.data import ObjectTracks
from gns.graph import MeshLibrary
from datagen.shards import Dataset
from gns.spec import ModelSpec
from gns.checkpoint import build_simulator, read_checkpoint
from gns.train import train

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "gns_tiny.toml"
# few steps, all inside the normalisers' accumulation, every window drawn with noise and rotation
SETTINGS = ["train.steps=6", "train.batch_size=5", "train.checkpoint_every=3", "train.log_every=1",
            "valid.every=0", "train.threads=1", "features.normalizer_steps=4", "features.collision_radius=2.0"]


def torchrun(data, run, *extra):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
           "-m", "gns.cli", "train", "--data", str(data), "--out", str(run), "--config", str(TINY),
           "--set", *SETTINGS, *extra]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ddp")
    # 1-3 objects of 8 (cube) or 64 (cylinder) vertices a scene: the processes' shares hold
    # different node counts, collision edges come and go, materials vary
    assert datagen_main(["toss", "--out", str(tmp / "data"), "--objects", "1-3", "--scenes", "6", "--frames", "10",
                         "--shapes", "cube,cylinder", "--quiet"]) == 0
    data = tmp / "data"
    train(data, tmp / "one", build_config(path=TINY, overrides=SETTINGS), log=lambda _: None)
    two = torchrun(data, tmp / "two")
    assert two.returncode == 0, two.stderr[-3000:]
    return data, tmp, two


def test_two_processes_match_one_on_the_same_global_batch(runs):
    data, tmp, _ = runs
    one, two = read_checkpoint(tmp / "one" / "latest.pt"), read_checkpoint(tmp / "two" / "latest.pt")
    assert one["step"] == two["step"] == 6
    assert one["model"].keys() == two["model"].keys()      # no DDP prefix in the checkpoint
    changed = 0
    for key, a in one["model"].items():
        b = two["model"][key]
        if a.is_floating_point():
            scale = a.abs().max().clamp(min=1e-3)
            assert (a - b).abs().max() <= 1e-5 * scale, key   # summation order only
        else:
            assert torch.equal(a, b), key
    # the runs trained: their weights left the common initialisation
    torch.manual_seed(0)
    start = build_simulator(build_config(path=TINY, overrides=SETTINGS), ModelSpec.from_dict(one["spec"]))
    assert any(not torch.allclose(start.state_dict()[k], one["model"][k]) for k in one["model"] if "network" in k)
    # normaliser statistics are those of the whole global batch in both runs
    for count in ("node_normalizers.velocity.count", "collision_normalizers.collision_relative.count"):
        assert one["model"][count] == two["model"][count] > 0
    # identical data stream: resuming either continues the same training
    assert one["rng"]["numpy"] == two["rng"]["numpy"]


def test_only_rank_zero_writes_and_logs_the_global_loss(runs):
    _, tmp, two = runs
    lines = (tmp / "two" / "metrics.jsonl").read_text().splitlines()
    ref = (tmp / "one" / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == len(ref) == 6                     # one writer, one line a step
    import json
    for a, b in zip(lines, ref):
        assert json.loads(a)["loss"] == pytest.approx(json.loads(b)["loss"], rel=1e-5)
    assert two.stdout.count("training at step 0 of 6 on 2 processes") == 1
    assert sorted(p.name for p in (tmp / "two").iterdir()) == sorted(p.name for p in (tmp / "one").iterdir())


def test_two_processes_resume_where_they_stopped(runs):
    data, tmp, _ = runs
    more = torchrun(data, tmp / "two", "train.steps=8", "--resume")
    assert more.returncode == 0, more.stderr[-3000:]
    assert read_checkpoint(tmp / "two" / "latest.pt")["step"] == 8


def test_share_splits_the_global_batch_into_disjoint_contiguous_parts():
    for size in (1, 2, 3):
        for batch in (size, 5, 8):
            parts = [share(batch, World(r, size)) for r in range(size)]
            assert parts[0][0] == 0 and parts[-1][1] == batch
            assert all(a[1] == b[0] for a, b in zip(parts, parts[1:]))
            assert max(hi - lo for lo, hi in parts) - min(hi - lo for lo, hi in parts) <= 1


def test_a_share_of_a_batch_holds_exactly_its_windows(tmp_path):
    ds = Dataset(write_toss_dataset(tmp_path / "d", train=4, valid=0, frames=8))
    tracks = ObjectTracks(ds.load("train"), MeshLibrary(ds.meshes))
    full = tracks.batch(torch.tensor([0, 5, 9, 3, 7]))
    lo_part, hi_part = windows(full, 0, 2), windows(full, 2, 5)
    assert lo_part.graph.num_graphs + hi_part.graph.num_graphs == full.graph.num_graphs
    torch.testing.assert_close(torch.cat([lo_part.history, hi_part.history]), full.history, rtol=0, atol=0)
    alone = tracks.batch(torch.tensor([9, 3, 7]))
    torch.testing.assert_close(hi_part.history, alone.history, rtol=0, atol=0)
    for a, b in ((hi_part.graph.mesh_edges.senders, alone.graph.mesh_edges.senders),
                 (hi_part.graph.faces, alone.graph.faces), (hi_part.graph.graph_scene, alone.graph.graph_scene),
                 (hi_part.graph.node_graph, alone.graph.node_graph)):
        assert torch.equal(a, b)


def test_a_global_batch_smaller_than_the_processes_is_one_line(tmp_path):
    data = write_toss_dataset(tmp_path / "d", train=2, valid=0, frames=6)
    out = torchrun(data, tmp_path / "run", "train.batch_size=1")
    assert out.returncode != 0
    assert "error: train.batch_size=1 is the global batch, split over 2 processes" in out.stderr
    # torchrun adds its own report of the failed processes; ours add no traceback
    assert "gns/train.py" not in out.stderr and "gns/cli.py" not in out.stderr
