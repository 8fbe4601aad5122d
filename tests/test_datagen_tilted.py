"""datagen.tilted: the 45-degree drop scene, PyBullet's side, the side classifier, the training scenes."""

import hashlib

import numpy as np
import pytest

from datagen.scenes import load_config
from datagen.inspect import rotate
from datagen.scenes import get_shape
from datagen.toss import simulate
from datagen.tilted import side, tilted_scene, training_scene


@pytest.fixture(scope="module")
def cfg():
    return load_config(sets=["scene.frames=36", "scene.shapes=['cube']"])


def world_vertices(obj):
    return rotate(obj.quaternion, get_shape(obj.shape).vertices * obj.scale) + obj.position


@pytest.mark.parametrize("angle", [10.0, 44.0, 45.0, 46.0, 80.0])
def test_drop_scene_stands_on_its_edge_touching_the_floor(cfg, angle):
    obj = tilted_scene(cfg, angle).objects[0]
    v = world_vertices(obj)
    low = np.isclose(v[:, 2], 0.0, atol=1e-12)
    assert v[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    assert low.sum() == 2                                   # an edge, not a face or a corner
    assert np.allclose(v[low, 0], 0.0, atol=1e-12)          # along y at x = 0
    assert np.ptp(v[low, 1]) == pytest.approx(obj.scale)
    # the centre's polar angle from the edge is 45 + tilt degrees
    x, z = obj.position[0], obj.position[2]
    assert np.degrees(np.arctan2(z, x)) == pytest.approx(45.0 + angle)
    assert obj.scale == cfg["sizes"]["large"] and not obj.velocity.any() and not obj.angular_velocity.any()


def test_pybullet_falls_back_below_45_degrees_and_over_the_edge_above(cfg):
    below = simulate(tilted_scene(cfg, 44.0), cfg)
    above = simulate(tilted_scene(cfg, 46.0), cfg)
    assert side(below.positions, 1.4) == 1
    assert side(above.positions, 1.4) == -1
    # lying flat on a face afterwards: centre half a size from the edge and half a size high
    assert abs(below.positions[-1, 0, 0]) == pytest.approx(0.7, abs=0.1)
    assert below.positions[-1, 0, 2] == pytest.approx(0.7, abs=0.02)


def test_side_classifier():
    track = np.zeros((5, 1, 3))
    track[-1, 0, 0] = 0.7
    assert side(track, 1.4) == 1
    track[-1, 0, 0] = -0.7
    assert side(track, 1.4) == -1
    track[-1, 0, 0] = 0.2                     # still near the edge: not fallen
    assert side(track, 1.4) == 0
    assert side(track, 1.4, edge_x=-0.7) == 1  # relative to the edge, not the origin
    track[-1, 0, 0] = np.nan
    assert side(track, 1.4) == 0


def test_training_scenes_mix_drops_and_tosses_and_repeat_with_the_seed(cfg):
    specs = [training_scene(cfg, 3, "train", i) for i in range(20)]
    heights = [o.position[2] for s in specs for o in s.objects]
    assert min(heights) < 1.0 < max(heights)  # drops sit on the floor, tosses start >= 1 up
    drops = [s.objects[0] for s in specs if not s.objects[0].velocity.any()]
    assert drops and len(drops) < len(specs)
    for o in drops:
        assert world_vertices(o)[:, 2].min() >= -1e-12
    again = training_scene(cfg, 3, "train", 7).objects[0]
    assert np.array_equal(again.position, specs[7].objects[0].position)


def test_drop_heights_up_to_one_size_and_the_default_unchanged(cfg):
    two = load_config(sets=["scene.frames=36", "scene.shapes=['cube', 'beveled_cube']"])
    high = [training_scene(two, 0, "train", i, max_heights=(0.05, 1.0)) for i in range(80)]
    drops = [s.objects[0] for s in high if not s.objects[0].velocity.any()]
    lows = [world_vertices(o)[:, 2].min() / o.scale for o in drops]
    assert min(lows) >= -1e-12 and max(lows) <= 1.0 and max(lows) > 0.5     # up to one size up
    assert sum(h < 0.05 for h in lows) >= len(lows) // 4                      # and half near the floor
    assert {o.shape for o in drops} == {"cube", "beveled_cube"}
    # one height draws nothing more: the scenes of before the parameter, bit for bit (the hash of
    # their poses as the code without max_heights made them)
    h = hashlib.sha256()
    for i in range(20):
        o = training_scene(cfg, 3, "train", i).objects[0]
        h.update(np.ascontiguousarray(o.position).tobytes())
        h.update(np.ascontiguousarray(o.quaternion).tobytes())
    assert h.hexdigest() == "90308ce2596a68ec106a4324215d50d9d032f4de7bf8f09765314fc6eb4dd857"
