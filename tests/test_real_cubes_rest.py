"""The coming-to-rest measurement (pipelines/real_cubes_rest.py) against physics on synthetic
tracks: constant velocity, constant spin about a fixed axis, rest; end and start alignment of
tracks of different lengths; the windows of model steps; the motion past a toss's end."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from datagen.contactnets import HALF_WIDTH_M
from datagen.shards import Scene, wxyz
from pipelines import real_cubes_rest as rest

RATE, STRIDE = 148.0, 8


def track(frames: int, velocity=(0.0, 0.0, 0.0), omega=0.0, axis=(0.0, 0.0, 1.0)):
    """Centres (T, 3) in half-widths moving at `velocity` (half-widths/s) and orientations (T, 4)
    wxyz turning at `omega` rad/s about `axis` from a tilted start, at the data's frame rate."""
    t = np.arange(frames) / RATE
    pos = np.array([0.3, -0.2, 1.0]) + t[:, None] * np.asarray(velocity)
    start = Rotation.from_euler("xyz", [0.4, -0.7, 1.1])
    axis = np.asarray(axis) / np.linalg.norm(axis)
    quat = wxyz((Rotation.from_rotvec(omega * t[:, None] * axis) * start).as_quat())
    return pos, quat


def test_constant_velocity_gives_its_speed_in_metres_and_no_spin():
    v = np.array([3.0, -4.0, 0.0])            # 5 half-widths/s
    m = rest.toss_motion(*track(8 * 12 + 1, velocity=v), STRIDE, RATE)
    assert m["speed"].shape == (12,)
    np.testing.assert_allclose(m["speed"], 5.0 * HALF_WIDTH_M, rtol=1e-12)
    np.testing.assert_allclose(m["spin"], 0.0, atol=1e-9)


@pytest.mark.parametrize("omega,axis", [(2.0, (0, 0, 1)), (11.5, (1.0, -2.0, 0.5)), (0.03, (0, 1, 0))])
def test_constant_spin_about_a_fixed_axis_gives_that_spin(omega, axis):
    m = rest.toss_motion(*track(8 * 9 + 1, omega=omega, axis=axis), STRIDE, RATE)
    np.testing.assert_allclose(m["spin"], omega, rtol=1e-9)
    np.testing.assert_allclose(m["speed"], 0.0, atol=1e-12)
    # the sign of a quaternion is no rotation
    pos, quat = track(8 * 9 + 1, omega=omega, axis=axis)
    quat[1::2] *= -1
    np.testing.assert_allclose(rest.toss_motion(pos, quat, STRIDE, RATE)["spin"], omega, rtol=1e-9)


def test_a_resting_track_is_at_rest_and_a_slow_slide_is_not():
    m = rest.toss_motion(*track(41), STRIDE, RATE)
    assert np.all(m["speed"] == 0) and np.all(m["spin"] < 1e-12)
    assert rest.at_rest(m["speed"], m["spin"]).all()
    slow = rest.toss_motion(*track(41, velocity=(2 * rest.REST_SPEED / HALF_WIDTH_M, 0, 0)), STRIDE, RATE)
    assert not rest.at_rest(slow["speed"], slow["spin"]).any()
    assert rest.at_rest(slow["speed"], slow["spin"], factor=4).all()


def test_a_track_must_be_whole_model_steps():
    with pytest.raises(ValueError, match="whole number"):
        rest.toss_motion(*track(20), STRIDE, RATE)


def test_end_and_start_alignment_of_tracks_of_different_lengths():
    a, b, c = np.array([1.0, 2.0, 3.0]), np.array([10.0, 20.0, 30.0, 40.0, 50.0]), np.array([7.0])
    end = rest.align_end([a, b, c])
    assert end.shape == (3, 5)
    np.testing.assert_array_equal(end[:, -1], [3, 50, 7])          # every toss's last step in the last column
    np.testing.assert_array_equal(end[0], [np.nan, np.nan, 1, 2, 3])
    start = rest.align_start([a, b, c])
    np.testing.assert_array_equal(start[:, 0], [1, 10, 7])
    np.testing.assert_array_equal(start[2], [7, np.nan, np.nan, np.nan, np.nan])
    np.testing.assert_array_equal(rest.align_end([a, b], 2), [[2, 3], [40, 50]])   # cut to the last n
    stats = rest.band(end)
    np.testing.assert_array_equal(stats["count"], [1, 1, 2, 2, 3])
    np.testing.assert_allclose(stats["mean"][-1], 20.0)
    np.testing.assert_allclose(stats["median"][-1], 7.0)


def test_windows_pick_the_whole_model_steps_inside_them():
    last = 96                                   # steps 0..11 span frames 0..96
    assert rest.step_window(last, last - 30, last, STRIDE) == slice(9, 12)    # frames 72..96: 3 steps
    assert rest.step_window(last, last - 10, last, STRIDE) == slice(11, 12)   # frames 88..96: 1 step
    assert rest.step_window(last, 16, 46, STRIDE) == slice(2, 5)              # 16..40
    assert rest.step_window(last, -1, last, STRIDE) == slice(0, 12)           # the whole toss
    w = rest.windows(last, 16)
    assert w[f"last {rest.WINDOW}"] == (66, 96) and w[f"first {rest.WINDOW} after the given frames"] == (16, 46)


def _scene(pos, quat):
    n = len(pos)
    return Scene(positions=pos[:, None], quaternions=quat[:, None], velocities=np.zeros((n, 1, 3)),
                 angular_velocities=np.zeros((n, 1, 3)), shape=["cube"], material=["acrylic"], scale=np.ones(1) * 2,
                 mass=np.ones(1), friction=np.ones(1), restitution=np.ones(1), attrs={"scene_id": 7})


def test_measure_reads_windows_and_rest_from_model_and_truth():
    frames = 8 * 12 + 1
    moving = _scene(*track(frames, velocity=(1.0, 0, 0), omega=3.0))
    still = _scene(*track(frames))
    errors = [{"position_error_pct": np.full((frames, 1), 2.0), "rotation_error_deg": np.full((frames, 1), 5.0)}]
    row, = rest.measure([moving], [still], errors, STRIDE, RATE)
    assert row["truth_at_rest"] and not row["model_at_rest"]
    last = row["windows"][f"last {rest.LAST}"]
    assert last["steps"] == 1 and last["truth_speed"] == 0
    assert last["model_speed"] == pytest.approx(HALF_WIDTH_M) and last["model_spin"] == pytest.approx(3.0)
    assert last["position_error_pct"] == 2.0 and last["rotation_error_deg"] == 5.0
    assert len(row["series"]["model_speed"]) == 12 - (rest.HISTORY - 1)   # the predicted steps only


def test_after_end_measures_the_slide_past_a_stopped_truth():
    frames = 8 * 5 + 1 + 3                      # the recording goes on 3 frames past the last model frame
    recorded = _scene(*track(frames))
    pos, quat = track(8 * 9 + 1, velocity=(0.5, 0, 0), omega=0.2)
    model = (pos[::STRIDE], quat[::STRIDE])     # the model's own rate: 5 steps in the toss, 4 past it
    a = rest.after_end(model, recorded, 5, STRIDE, RATE)
    np.testing.assert_allclose(a["model_speed"], 0.5 * HALF_WIDTH_M)
    np.testing.assert_allclose(a["model_spin"], 0.2)
    step = STRIDE / RATE
    np.testing.assert_allclose(a["model_slid_mm"], 1000 * 0.5 * HALF_WIDTH_M * step * np.arange(1, 5))
    np.testing.assert_allclose(a["model_turned_deg"], np.degrees(0.2 * step * np.arange(1, 5)))
    assert a["truth_end_speed"] == 0 and a["truth_slid_mm"] == 0 and a["truth_turned_deg"] < 1e-9
    assert a["truth_end_time_s"] == pytest.approx((3 - STRIDE / 2) / RATE)


def test_a_missing_source_folder_is_one_error_line(tmp_path, capsys):
    assert rest.main(["--src", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")]) == 2
    assert "is not a folder" in capsys.readouterr().err
