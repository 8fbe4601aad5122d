"""pipelines/error_breakdown.py: how the error spreads over scenes, rotation against position."""
import json

import numpy as np
import pytest
from gns_fixtures import write_toss_dataset

from gns.train import train
from pipelines.error_breakdown import binned, breakdown, main, worst_shares
from test_gns_train import quiet, tiny


def test_worst_shares_of_one_bad_scene_and_of_equal_scenes():
    one_bad = np.array([0.0] * 19 + [10.0])
    assert worst_shares(one_bad) == {"5%": 1.0, "10%": 1.0, "20%": 1.0, "50%": 1.0}
    equal = np.ones(20)
    assert worst_shares(equal) == pytest.approx({"5%": 0.05, "10%": 0.10, "20%": 0.20, "50%": 0.50})


def test_bins_split_frames_and_error_exactly():
    by = np.array([1.0, 2.0, 7.0, 30.0])
    values = np.array([1.0, 1.0, 2.0, 6.0])
    rows = binned(values, by, (0.0, 5.0, 10.0, np.inf))
    assert [r["share_of_frames"] for r in rows] == [0.5, 0.25, 0.25]
    assert [r["mean"] for r in rows] == [1.0, 2.0, 6.0]
    assert [r["share_of_error"] for r in rows] == [0.2, 0.2, 0.6]
    assert binned(values, by, (100.0, 200.0))[0]["mean"] is None   # an empty bin


def test_breakdown_of_constructed_errors():
    frames = np.zeros((4, 1))
    good = {"position_error_pct": frames + 1, "rotation_error_deg": frames + 1, "true_spin_deg": frames}
    bad = {"position_error_pct": frames + 60, "rotation_error_deg": frames + 90, "true_spin_deg": frames + 20}
    b = breakdown([good, good, good, bad])
    assert b["num_object_frames"] == 16
    assert b["scenes"]["rotation_error_deg"]["median"] == 1.0
    # the one scene far off in position holds all rotation error beyond 50% of the size
    assert b["rotation_by_position_error"][-1]["share_of_error"] == pytest.approx(90 / 93)
    assert b["rotation_by_true_spin"][-1]["share_of_frames"] == 0.25


@pytest.mark.filterwarnings("ignore:outside training")
def test_the_command_rolls_out_a_split_and_writes_json(tmp_path, capsys):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=2, frames=12)
    train(data, tmp_path / "run", tiny("train.steps=4", "valid.every=0", "features.normalizer_steps=2"), log=quiet)
    out = tmp_path / "b.json"
    assert main(["--run", str(tmp_path / "run"), "--data", str(data), "--split", "valid", "--free-flight",
                 "--symmetrize", "--json", str(out)]) == 0
    assert "share of rotation error" in capsys.readouterr().out
    b = json.loads(out.read_text())
    assert b["num_scenes"] == 2 and b["split"] == "valid"
    assert sum(r["share_of_frames"] for r in b["rotation_by_position_error"]) == pytest.approx(1.0)
    assert main(["--run", str(tmp_path / "nothing"), "--data", str(data)]) == 2


def test_meeting_labels_split_objects_by_their_first_meeting_with_another():
    import numpy as np
    from datagen.shards import Scene
    from pipelines.error_breakdown import by_meeting, meeting_labels
    cube = (np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)]), np.zeros((0, 3), int))
    T = 6
    x = np.zeros((T, 3, 3))
    x[:, 0, 0] = np.linspace(-3, 0, T)      # object 0 reaches object 1 (at the origin) at frame 5
    x[:, 2, 0] = 20.0                       # object 2 never comes near
    sc = Scene(x, np.tile([1.0, 0, 0, 0], (T, 3, 1)), np.zeros((T, 3, 3)), np.zeros((T, 3, 3)), ["cube"] * 3,
               ["metal"] * 3, np.ones(3), np.ones(3), np.ones(3), np.ones(3))
    labels = meeting_labels([sc], {"cube": cube})[0]
    radius_sum = 2 * np.sqrt(3) / 2                           # bounding spheres touch below this distance
    # on the way to frame t the gap is |x_t| less the radii and half of the 0.6 the object moves a frame
    first = int(np.argmax(np.abs(x[:, 0, 0]) < radius_sum + 0.3))
    assert labels[:, 2].tolist() == [0] * T
    assert labels[:, 0].tolist() == [1] * first + [2] * (T - first) == labels[:, 1].tolist()
    errors = [{"position_error_pct": np.arange(T * 3, dtype=float).reshape(T, 3),
               "rotation_error_deg": np.ones((T, 3))}]
    rows = by_meeting(errors, [labels])
    assert [r["group"] for r in rows][0].startswith("never") and abs(sum(r["share_of_frames"] for r in rows) - 1) < 1e-12


def test_objects_that_meet_between_two_frames_are_not_counted_as_never_near():
    import numpy as np
    from datagen.shards import Scene
    from pipelines.error_breakdown import meeting_labels, swept_touch
    cube = (np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)]), np.zeros((0, 3), int))
    T = 4
    x = np.zeros((T, 2, 3))
    x[:, 0, 0] = [-6.0, -2.0, 2.0, 6.0]     # object 0 flies past object 1 (at the origin), 4 a frame,
    x[:, 0, 1] = 0.5                        # 0.5 off its centre: the spheres (radius 0.87) meet between frames
    sc = Scene(x, np.tile([1.0, 0, 0, 0], (T, 2, 1)), np.zeros((T, 2, 3)), np.zeros((T, 2, 3)), ["cube"] * 2,
               ["metal"] * 2, np.ones(2), np.ones(2), np.ones(2), np.ones(2))
    assert not (np.linalg.norm(x[:, 0] - x[:, 1], axis=-1) < np.sqrt(3)).any()   # never touching at a frame
    # within reach from frame 1 on: the path from frame 0 ends 2.06 away, less than the radii and half the move
    assert swept_touch(sc, {"cube": cube}).tolist() == [[False, False], [True, True], [True, True], [True, True]]
    assert meeting_labels([sc], {"cube": cube})[0].tolist() == [[1, 1], [2, 2], [2, 2], [2, 2]]
    x[:, 0, 1] = 5.0                        # the same flight 5 to the side: farther than radii and half a move
    assert not swept_touch(sc, {"cube": cube}).any()
    assert (meeting_labels([sc], {"cube": cube})[0] == 0).all()
