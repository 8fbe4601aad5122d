"""What gns.load(...).state / .rollout / .step do with bad input: one DataError (or TypeError)
line naming the argument and the object, never an all-NaN trajectory or a numpy error from
deep inside (docs/reliability.md, the Python API rows)."""
import math
import time
import warnings

import numpy as np
import pytest
import torch

import gns
from plumbing import DataError

NAN, INF = float("nan"), float("inf")


@pytest.fixture(scope="module")
def model():
    """The zoo's MOVi-A model: materials are inputs, a floor at z = 0, 12 steps a second."""
    return gns.load("movi_a")


def two(**changes):
    """Two valid objects, each a scene of its own (so no warning is due), with `changes`."""
    s = dict(shapes=["sphere", "beveled_cube"], positions=[[0.0, 0.0, 1.0], [3.0, 0.0, 1.0]],
             quaternions=[[1.0, 0.0, 0.0, 0.0], [0.9, 0.1, 0.0, 0.3]], velocities=[[1.0, 0.0, 2.0], [0.0, 1.0, 0.0]],
             angular_velocities=[[0.0, 0.0, 3.0], [1.0, 0.0, 0.0]], scales=1.0, friction=0.5, restitution=0.5,
             scene=[0, 1])
    s.update(changes)
    return {k: v for k, v in s.items() if v is not ...}


def history_of(model, s):
    """The free-flight history state() builds for `s`, as history= takes it (numpy, editable)."""
    from gns.api import history_poses, matrix_to_quat, quat_to_matrix
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    pos, rot = history_poses(t(s["positions"]), quat_to_matrix(t(s["quaternions"])), t(s["velocities"]),
                             t(s["angular_velocities"]), model.dt, torch.as_tensor(model.gravity))
    return pos[:2].numpy().copy(), matrix_to_quat(rot[:2]).numpy().copy()


def one_line(excinfo) -> str:
    text = str(excinfo.value)
    assert "\n" not in text and text
    return text


def test_the_valid_input_rolls_out_without_a_word(model):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = model.rollout(**two(), steps=2)
    assert torch.isfinite(out.positions).all()


@pytest.mark.parametrize("call", ["rollout", "state"])
@pytest.mark.parametrize("name", ["shapes", "positions", "quaternions"])
def test_a_required_argument_given_as_none_is_one_line_naming_it(model, call, name):
    s = two(**{name: None})
    with pytest.raises(DataError, match=f"^{name} is None") as e:
        getattr(model, call)(**s, **({"steps": 2} if call == "rollout" else {}))
    one_line(e)


@pytest.mark.parametrize("name, value, match", [
    ("positions", [[0.0, 0.0, 1.0], [NAN, 0.0, 1.0]], r"positions of object 1 is not finite \(\[nan, 0.0, 1.0\]\)"),
    ("positions", [[INF, 0.0, 1.0], [3.0, 0.0, 1.0]], "positions of object 0 is not finite"),
    ("velocities", [[1.0, 0.0, 2.0], [0.0, -INF, 0.0]], "velocities of object 1 is not finite"),
    ("angular_velocities", [[NAN, 0.0, 0.0], [1.0, 0.0, 0.0]], "angular_velocities of object 0 is not finite"),
    ("quaternions", [[1.0, 0.0, 0.0, 0.0], [NAN, 0.0, 0.0, 1.0]], "quaternions of object 1 is not finite"),
    ("scales", [1.0, NAN], "scales of object 1 is not finite"),
    ("scales", INF, "scales is not finite"),
    ("friction", [0.5, INF], "friction of object 1 is not finite"),
    ("restitution", NAN, "restitution is not finite"),
])
def test_a_non_finite_input_is_one_line_naming_it_and_the_object(model, name, value, match):
    with pytest.raises(DataError, match=match) as e:
        model.rollout(**two(**{name: value}), steps=2)
    one_line(e)


@pytest.mark.parametrize("part, frame, bad, match", [
    (0, 0, NAN, r"history positions of object 1 at t - 2 dt is not finite"),
    (0, 1, INF, r"history positions of object 1 at t - dt is not finite"),
    (1, 0, NAN, r"history quaternions of object 1 at t - 2 dt is not finite"),
    (1, 1, 0.0, r"history quaternions of object 1 at t - dt is zero"),
    (1, 0, 0.0, r"history quaternions of object 1 at t - 2 dt is zero"),
])
def test_bad_history_is_one_line_not_an_svd_failure(model, part, frame, bad, match):
    s = two()
    history = history_of(model, s)
    history[part][frame, 1] = bad
    past = two(velocities=..., angular_velocities=...)
    model.rollout(**past, history=history_of(model, s), steps=1)          # the true history is fine
    with pytest.raises(DataError, match=match) as e:
        model.rollout(**past, history=history, steps=1)
    one_line(e)


def test_a_history_that_is_not_a_pair_is_one_line(model):
    with pytest.raises(DataError, match=r"history must be \(positions \(2, 2, 3\), quaternions \(2, 2, 4\)\)") as e:
        model.rollout(**two(velocities=..., angular_velocities=...), history=np.zeros((2, 2, 3)), steps=1)
    one_line(e)


def test_a_zero_quaternion_names_the_object(model):
    with pytest.raises(DataError, match="quaternions of object 1 is zero") as e:
        model.state(**two(quaternions=[[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))
    one_line(e)


def test_a_spin_of_half_a_turn_per_step_or_more_is_refused_with_the_true_speed(model):
    limit = math.pi / model.dt                           # 37.7 rad/s at 12 steps/s
    for speed in (72.0, 75.4, limit):
        with pytest.raises(DataError, match=rf"angular_velocities of object 1: {speed:.4g} rad/s is half a turn "
                                            rf"or more per model step \(limit pi / dt = {limit:.4g} rad/s") as e:
            model.rollout(**two(angular_velocities=[[0.0, 0.0, 1.0], [0.0, 0.0, speed]]), steps=1)
        one_line(e)
    # just below the limit: outside training (29 rad/s), and the warning gives the true speed
    with pytest.warns(UserWarning, match=r"outside training: angular speed .*36\.5 rad/s"):
        model.rollout(**two(angular_velocities=[[0.0, 0.0, 1.0], [0.0, 0.0, 36.5]]), steps=1)


@pytest.mark.parametrize("name, value, match", [
    ("positions", [[0.0, 0.0, 1.0]], r"positions has shape \(1, 3\), expected \(2, 3\)"),
    ("positions", [0.0, 0.0, 1.0], r"positions has shape \(3,\), expected \(2, 3\)"),
    ("quaternions", [[1.0, 0.0, 0.0, 0.0]], r"quaternions has shape \(1, 4\), expected \(2, 4\)"),
    ("velocities", [[1.0, 0.0, 0.0]], r"velocities has shape \(1, 3\), expected \(2, 3\)"),
    ("angular_velocities", 0.0, r"angular_velocities has shape \(\), expected \(2, 3\)"),
    ("scales", [1.0], r"scales has shape \(1,\), expected one number or \(2,\)"),
    ("friction", [[0.5, 0.5]], r"friction has shape \(1, 2\), expected one number or \(2,\)"),
])
def test_one_row_for_several_objects_is_refused(model, name, value, match):
    with pytest.raises(DataError, match=match) as e:
        model.rollout(**two(**{name: value}), steps=1)
    one_line(e)


def test_one_number_for_a_property_of_every_object_is_broadcast(model):
    a = model.rollout(**two(scales=1.2, friction=0.6, restitution=0.4), steps=2)
    b = model.rollout(**two(scales=[1.2, 1.2], friction=[0.6, 0.6], restitution=[0.4, 0.4]), steps=2)
    torch.testing.assert_close(a.positions, b.positions, rtol=0, atol=0)
    one = dict(shapes=["sphere"], positions=[0.0, 0.0, 1.0], quaternions=[1.0, 0.0, 0.0, 0.0], friction=0.5,
               restitution=0.5)                                      # one object: a row without its axis is it
    assert model.rollout(**one, steps=1).positions.shape == (2, 1, 3)


@pytest.mark.parametrize("name, value, match", [
    ("positions", [[0.0, 0.0, 1.0], [0.0, 0.0]], r"positions is ragged or holds something that is not a number"),
    ("positions", "0 0 1", r"positions must be numbers, got the text '0 0 1'"),
    ("quaternions", [["1", "0", "0", "0"], ["1", "0", "0", "0"]], r"quaternions must be numbers, got text"),
    ("velocities", [[1.0, None, 0.0], [0.0, 0.0, 0.0]], r"velocities is ragged or holds something that is not a number"),
    ("scales", "big", r"scales must be numbers, got the text 'big'"),
    ("friction", [0.5, "x"], r"friction must be numbers, got text"),
    ("restitution", [True, False], r"restitution must be numbers, got booleans"),
    ("scene", ["a", "b"], r"scene must be whole numbers \(one scene number per object\), got text"),
    ("scene", [0.5, 1.0], r"scene must be whole numbers \(one scene number per object\), got \[0.5, 1.0\]"),
    ("shapes", ["sphere", 3], r"shapes must be mesh names \(text\), got 3"),
])
def test_ragged_or_text_input_is_one_line_naming_it(model, name, value, match):
    with pytest.raises(DataError, match=match) as e:
        model.rollout(**two(**{name: value}), steps=1)
    one_line(e)


def test_ragged_history_is_one_line(model):
    pos, quat = history_of(model, two())
    ragged = [pos[0].tolist(), pos[1].tolist()[:1]]
    with pytest.raises(DataError, match="history positions is ragged") as e:
        model.rollout(**two(velocities=..., angular_velocities=...), history=(ragged, quat), steps=1)
    one_line(e)


@pytest.mark.parametrize("name, value, match", [
    ("scales", [1.0, 0.0], r"scales of object 1 is 0: a size must be > 0"),
    ("scales", -1.0, r"scales is -1: a size must be > 0"),
    ("friction", [-0.1, 0.5], r"friction of object 0 is -0.1: it must be >= 0"),
    ("restitution", [0.5, 1.5], r"restitution of object 1 is 1.5: it must be in \[0, 1\]"),
    ("restitution", -0.2, r"restitution is -0.2: it must be in \[0, 1\]"),
])
def test_unphysical_values_are_refused_not_only_warned_about(model, name, value, match):
    with pytest.raises(DataError, match=match) as e:
        model.rollout(**two(**{name: value}), steps=1)
    one_line(e)


def test_the_bounds_themselves_are_physical(model):
    with pytest.warns(UserWarning, match="outside training"):   # outside the trained 0.4-0.8, 0.3-0.7; but allowed
        model.rollout(**two(friction=0.0, restitution=[0.0, 1.0]), steps=1)


def test_an_object_starting_below_the_floor_is_refused(model):
    # a unit cube (half-width 0.5 x scale) whose centre is 0.4 above the floor: 0.1 = 10% of its size below it
    with pytest.raises(DataError, match=r"object 1 \(beveled_cube\) starts 0.1 below the floor \(z = 0; allowed 5%") as e:
        model.rollout(**two(positions=[[0.0, 0.0, 1.0], [3.0, 0.0, 0.4]], quaternions=[[1.0, 0.0, 0.0, 0.0]] * 2),
                      steps=1)
    one_line(e)
    with pytest.raises(DataError, match=r"object 0 \(beveled_cube\) starts 1.5 below the floor"):
        model.rollout(**two(shapes=["beveled_cube", "sphere"], positions=[[0.0, 0.0, -1.0], [3.0, 0.0, 1.0]],
                            quaternions=[[1.0, 0.0, 0.0, 0.0]] * 2), steps=1)
    # resting on it, or a few % into it (as measured data are): fine
    model.rollout(**two(shapes=["sphere", "sphere"], positions=[[0.0, 0.0, 0.5], [3.0, 0.0, 0.48]],
                        velocities=[[0.0, 0.0, 0.0]] * 2, angular_velocities=[[0.0, 0.0, 0.0]] * 2), steps=1)
    # given history poses are checked too
    s = two()
    history = history_of(model, s)
    history[0][0, 1, 2] = -2.0
    with pytest.raises(DataError, match=r"object 1 \(beveled_cube\) at t - 2 dt starts .* below the floor"):
        model.rollout(**two(velocities=..., angular_velocities=...), history=history, steps=1)


@pytest.mark.parametrize("bad", [None, "state", {"positions": [[0, 0, 1]]}])
def test_step_of_something_that_is_not_a_state_is_one_line(model, bad):
    with pytest.raises(TypeError, match=r"step\(\) takes the State of model.state\(\.\.\.\) or of an earlier step, got") as e:
        model.step(bad)
    one_line(e)


def test_objects_starting_inside_each_other_warn_once_and_cheaply(model):
    n = 1000
    pile = dict(shapes=["sphere"] * n, positions=np.tile([0.0, 0.0, 2.0], (n, 1)), quaternions=np.tile([1.0, 0, 0, 0], (n, 1)),
                friction=0.5, restitution=0.5, scene=np.zeros(n, int))
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.state(**pile)
    seconds = time.perf_counter() - t0
    overlap = [w for w in caught if "start inside each other" in str(w.message)]
    assert len(overlap) == 1 and f"{n * (n - 1) // 2} pairs of objects" in str(overlap[0].message), [str(w.message) for w in caught]
    assert "\n" not in str(overlap[0].message) and overlap[0].filename == __file__
    assert seconds < 10, seconds             # the whole state of 1000 objects; the check itself is a KD-tree query
    # touching but not inside each other (unit spheres 1 apart, cubes face to face), or in scenes of their own: no word
    for s in (dict(shapes=["sphere", "sphere"], positions=[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]),
              dict(shapes=["beveled_cube", "beveled_cube"], positions=[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]],
                   quaternions=[[1.0, 0.0, 0.0, 0.0]] * 2),
              dict(shapes=["sphere", "sphere"], positions=[[0.0, 0.0, 1.0]] * 2, scene=[0, 1])):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model.state(**two(**s))
        assert not [w for w in caught if "inside each other" in str(w.message)], [str(w.message) for w in caught]
