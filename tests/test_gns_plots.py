"""Each plot writes a readable PNG/GIF; kept fast with small scenes and low dpi."""
import numpy as np
import pytest
from PIL import Image

from datagen.scenes import get_shape
from datagen.shards import Scene
from gns.geometry import quat_from_axis_angle
from gns.charts import plot_curve
from gns.plots import animate_rollout, contact_frames, plot_error_vs_time, plot_trajectory

T = 12


def meshes():
    return {n: (get_shape(n).vertices, get_shape(n).faces) for n in ("cube", "sphere")}


def toss(shapes=("cube",), shift=0.0):
    """A cube falling onto the floor (z = 0) and resting, moving along +x and spinning about z."""
    N = len(shapes)
    t = np.arange(T)
    z = np.maximum(0.5, 3.0 - 0.05 * t**2)                      # reaches the floor at t ~ 7.1
    pos = np.stack([0.3 * t + shift, 0.1 * t, z], axis=1)[:, None].repeat(N, axis=1)
    pos[:, :, 1] += 2.0 * np.arange(N)                          # objects side by side
    quat = quat_from_axis_angle([0, 0, 1], 0.1 * t)[:, None].repeat(N, axis=1)
    zeros = np.zeros((T, N, 3))
    return Scene(positions=pos, quaternions=quat, velocities=zeros, angular_velocities=zeros,
                 shape=list(shapes), material=["metal"] * N, scale=np.ones(N), mass=np.ones(N),
                 friction=np.full(N, 0.4), restitution=np.full(N, 0.3), attrs={"scene_id": 3})


def assert_png(path):
    assert path.exists() and path.stat().st_size > 0
    with Image.open(path) as im:
        assert im.format == "PNG" and im.size[0] > 100 and im.size[1] > 100


def test_contact_frames():
    # z = 3 - 0.05 t^2 is 0.55 at t = 7 (lowest vertex 0.05 up, beyond the 2% tolerance), floor from 8
    assert contact_frames(toss(), meshes()).tolist() == list(range(8, T))
    assert contact_frames(toss(), meshes(), tol=0.06).tolist() == list(range(7, T))


@pytest.mark.parametrize("dt", [None, 1 / 12])
def test_plot_trajectory(tmp_path, dt):
    out = plot_trajectory(toss(shift=0.2), toss(), meshes(), tmp_path / "sub" / "traj.png", dt=dt,
                          unit="m", dpi=40)
    assert_png(out)


def test_plot_error_vs_time_one_and_several_models(tmp_path):
    one = {"position_error_pct": np.linspace(0, 10, T), "rotation_error_deg": np.linspace(0, 5, T)}
    assert_png(plot_error_vs_time(one, tmp_path / "one.png", dpi=40))
    several = {"gns": {**one, "penetration_pct": np.zeros((T, 2)), "true_penetration_pct": np.ones(T)},
               "bullet": {k: 2 * v for k, v in one.items()}}
    assert_png(plot_error_vs_time(several, tmp_path / "several.png", dt=0.1, dpi=40))
    with pytest.raises(ValueError, match="no known metric"):
        plot_error_vs_time({"loss": np.ones(3)}, tmp_path / "bad.png")


def test_animate_rollout_frame_count(tmp_path):
    out = animate_rollout(toss(("cube", "sphere"), shift=0.2), toss(("cube", "sphere")), meshes(),
                          tmp_path / "anim.gif", fps=10, stride=2, dpi=30)
    with Image.open(out) as im:
        assert im.format == "GIF" and im.n_frames == len(range(0, T, 2))
    out = animate_rollout(toss(), toss(), meshes(), tmp_path / "short.gif", max_frames=3, dpi=30)
    with Image.open(out) as im:
        assert im.n_frames == 3


def test_plot_curve(tmp_path):
    xs = [8, 16, 32, 64]
    ys = {"gns": np.array([[40, 42], [30, 29], [20, 21], [15, 16]]), "other": [50, np.nan, 30, 25]}
    assert_png(plot_curve(xs, ys, tmp_path / "curve.png", baseline={"bullet": 12.0}, dpi=40))
    assert_png(plot_curve(xs, {"gns": [4, 3, 2, 1]}, tmp_path / "lin.png", baseline=2.0, log2=False, dpi=40))
