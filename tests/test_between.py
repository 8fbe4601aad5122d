"""The reader of the frames between a strided model's steps (gns.between), fitted on bouncing tosses."""
import numpy as np
import pytest
from gns_fixtures import FRAME_RATE, cube_meshes, toss_scene, write_toss_dataset
from test_gns_train import quiet, tiny

from datagen.shards import Scene
from gns.at_data_rate import upsample_scene
from gns.between import BetweenReader, fit
from gns.metrics import position_error_pct, rotation_error_deg
from plumbing import DataError

STRIDE = 4


@pytest.fixture(scope="module")
def reader():
    rng = np.random.default_rng(0)
    return fit([toss_scene(rng, 41, "metal") for _ in range(60)], STRIDE, seed=0)


def new_tosses(n=20):
    rng = np.random.default_rng(1)           # tosses the reader was not fitted on
    return [toss_scene(rng, 41, "metal") for _ in range(n)]


def errors(up: Scene, truth: Scene) -> tuple[float, float]:
    return (float(position_error_pct(up.positions, truth.positions, truth.scale).mean()),
            float(rotation_error_deg(up.quaternions, truth.quaternions).mean()))


def test_the_reader_keeps_the_model_frames_and_reads_bounces_better_than_the_spline(reader):
    learned, spline = [], []
    for full in new_tosses():
        coarse = full.every(STRIDE)
        up, truth = upsample_scene(coarse, STRIDE, full, FRAME_RATE, reader)
        assert up.num_frames == truth.num_frames == 41 and up.attrs["read_between"] == "learned"
        assert np.allclose(up.positions[::STRIDE], coarse.positions, rtol=0, atol=1e-12)
        assert np.allclose(up.quaternions[::STRIDE], coarse.quaternions, rtol=0, atol=1e-12)
        learned.append(errors(up, truth))
        spline.append(errors(*upsample_scene(coarse, STRIDE, full, FRAME_RATE)))
    learned, spline = np.mean(learned, axis=0), np.mean(spline, axis=0)
    # a bounce inside a step: the spline rings around the kink, the reader has seen such kinks
    assert learned[0] < 0.7 * spline[0]
    assert learned[1] < 0.5        # constant spin: slerp is exact, the reader must not spoil it


def test_the_reading_turns_with_the_scene(reader):
    from gns.geometry import quat_from_axis_angle, quat_multiply
    coarse = new_tosses(1)[0].every(STRIDE)
    angle = 0.7
    turn = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.array([angle]))[0]
    c, s = np.cos(angle), np.sin(angle)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    p, q = reader.read(coarse.positions, coarse.quaternions, coarse.scale)
    tp, tq = reader.read(coarse.positions @ rz.T, quat_multiply(turn, coarse.quaternions), coarse.scale)
    np.testing.assert_allclose(tp, p @ rz.T, rtol=0, atol=1e-5)
    assert rotation_error_deg(tq, quat_multiply(turn, q)).max() < 1e-3


def test_a_reader_needs_a_step_of_several_frames():
    with pytest.raises(DataError, match="every recorded frame"):
        BetweenReader(1)


def test_export_fits_the_reader_and_eval_reads_by_it(tmp_path):
    from gns.evaluate import evaluate_run
    from gns.train import train
    from gns.zoo import export_model
    data = write_toss_dataset(tmp_path / "data", train=6, valid=2, frames=24)
    run = tmp_path / "run"
    train(data, run, tiny("features.frame_stride=2", "train.steps=3", "valid.every=0"), log=quiet)
    model = export_model(run / "latest.pt", tmp_path / "model.pt", between=data)
    learned, *_ = evaluate_run(model, data, "valid", progress=False, at_data_rate=True)
    spline, *_ = evaluate_run(model, data, "valid", progress=False, at_data_rate=True, between="spline")
    assert (learned["read_between"], spline["read_between"]) == ("learned", "spline")
    assert learned["position_error_pct"] != spline["position_error_pct"]
    own, *_ = evaluate_run(model, data, "valid", progress=False)
    assert own["read_between"] is None            # at its own frames nothing is read between
    # gns rollout writes the same reading: every recorded frame, the model's own ones kept
    from datagen.shards import Dataset
    from gns.rollout_dataset import rollout_run
    rollout_run(model, data, tmp_path / "every", "valid", at_data_rate=True)
    rollout_run(model, data, tmp_path / "own", "valid")
    every, own = Dataset(tmp_path / "every"), Dataset(tmp_path / "own")
    assert every.frame_rate == FRAME_RATE and own.frame_rate == FRAME_RATE / 2
    assert every.meta["rollout"]["read_between"] == "learned" and every.meta["rollout"]["given_frames"] == 5
    a, b = every.load("valid")[0], own.load("valid")[0]
    assert a.num_frames == 2 * b.num_frames - 1
    np.testing.assert_allclose(a.positions[::2], b.positions, rtol=0, atol=1e-12)
    # a model that steps every frame has nothing between; data at another rate is refused
    train(data, tmp_path / "plain", tiny("train.steps=1", "valid.every=0"), log=quiet)
    with pytest.raises(DataError, match="every recorded frame"):
        export_model(tmp_path / "plain" / "latest.pt", tmp_path / "plain.pt", between=data)
    assert not (tmp_path / "plain.pt").exists()
    other = write_toss_dataset(tmp_path / "other", train=2, valid=0, frames=24)
    meta = (other / "metadata.json").read_text().replace(f'"frame_rate": {FRAME_RATE}', '"frame_rate": 30')
    (other / "metadata.json").write_text(meta)
    with pytest.raises(DataError, match="recorded at 30"):
        export_model(run / "latest.pt", tmp_path / "other.pt", between=other)


def test_the_python_api_reads_a_rollout_at_every_recorded_frame():
    import gns
    import torch
    for order in ("wxyz", "xyzw"):
        model = gns.load("real_cubes", quaternion_order=order)
        q0 = [1.0, 0, 0, 0] if order == "wxyz" else [0, 0, 0, 1.0]
        out = model.rollout(["cube"], positions=[[0, 0, 3.0]], quaternions=[q0], velocities=[[5.0, 0, 0]],
                            angular_velocities=[[0, 3.0, 0]], steps=12, scales=2.0)
        positions, quaternions, dt = model.every_frame(out)
        assert positions.shape == (12 * 8 + 1, 1, 3) and quaternions.shape == (12 * 8 + 1, 1, 4)
        assert dt == pytest.approx(out.dt / 8)
        torch.testing.assert_close(positions[::8], out.positions.double(), rtol=0, atol=1e-9)
        torch.testing.assert_close(quaternions[::8], out.quaternions.double(), rtol=0, atol=1e-6)
        spline, _, _ = model.every_frame(out, between="spline")
        assert (positions - spline).abs().max() > 1e-3      # the file's reader, not the spline
        # free flight first: both read the parabola between the first steps alike
        assert (positions[:9] - spline[:9]).abs().max() < 0.05
    with pytest.raises(DataError, match="'learned' or 'spline'"):
        model.every_frame(out, between="akima")
