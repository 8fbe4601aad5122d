"""gns.evaluate: scoring predicted scenes against the truth."""
from dataclasses import replace

import numpy as np
from gns_fixtures import write_toss_dataset

import gns.plots
from datagen.shards import Dataset
from gns import metrics
from gns.evaluate import score_predictions


def test_scoring_computes_each_scenes_errors_once_and_gives_the_same_numbers(tmp_path, monkeypatch):
    ds = Dataset(write_toss_dataset(tmp_path / "data", train=3, valid=0, frames=12))
    true = ds.load("train")
    rng = np.random.default_rng(0)
    pred = [replace(sc, positions=sc.positions + rng.normal(0.0, 0.05, sc.positions.shape),
                    quaternions=np.roll(sc.quaternions, 1, axis=0)) for sc in true]
    floor_z = float(ds.floor["z"])
    # each summary computing its errors itself, as an evaluation did before
    expect = metrics.evaluate_scenes(pred, true, ds.meshes, floor_z=floor_z)
    expect_per_scene = metrics.per_scene_means(pred, true, ds.meshes, floor_z)
    expect_curves = metrics.per_frame_curves(pred, true, ds.meshes, floor_z)

    calls = []
    per_frame_errors = metrics.per_frame_errors
    monkeypatch.setattr(metrics, "per_frame_errors", lambda *a, **k: calls.append(1) or per_frame_errors(*a, **k))
    curves = {}
    plot_error_vs_time = gns.plots.plot_error_vs_time
    monkeypatch.setattr(gns.plots, "plot_error_vs_time",
                        lambda c, *a, **k: curves.update(c) or plot_error_vs_time(c, *a, **k))
    results = score_predictions(pred, true, ds, 1.0, tmp_path / "plots")

    assert len(calls) == len(true)
    assert results["per_scene"] == expect_per_scene
    assert {k: v for k, v in results.items() if k in expect} == expect
    assert curves.keys() == expect_curves.keys() - {"count"}
    for k, v in curves.items():
        np.testing.assert_array_equal(v, expect_curves[k])
