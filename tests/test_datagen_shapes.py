import numpy as np
import pytest
import trimesh

from datagen.scenes import SHAPES, get_shape, parse_shapes


@pytest.mark.parametrize("name", SHAPES)
def test_unit_asset_is_convex_watertight_and_centred(name):
    s = get_shape(name)
    mesh = trimesh.Trimesh(s.vertices, s.faces, process=False)
    assert mesh.is_watertight
    assert mesh.is_convex
    assert mesh.is_winding_consistent and mesh.volume > 0  # outward faces
    np.testing.assert_allclose(s.vertices.min(0), -0.5, atol=1e-12)
    np.testing.assert_allclose(s.vertices.max(0), 0.5, atol=1e-12)
    np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-9)


@pytest.mark.parametrize("name, low, high", [("cube", 8, 8), ("beveled_cube", 51, 64), ("cylinder", 51, 64), ("sphere", 51, 64)])
def test_vertex_counts_match_the_paper(name, low, high):
    assert low <= len(get_shape(name).vertices) <= high


def test_mass_and_inertia_scale_like_a_solid():
    cube = get_shape("cube")
    assert cube.mass(2.0, 3.0) == pytest.approx(2.0 * 27.0)
    # Solid cube of side a: I = m a^2 / 6.
    m = cube.mass(2.0, 3.0)
    np.testing.assert_allclose(cube.inertia_diagonal(2.0, 3.0), m * 9.0 / 6.0)


def test_cylinder_inertia_close_to_analytic():
    # A 32-gon prism is nearly the solid cylinder r=0.5, h=1: Izz = m r^2 / 2.
    c = get_shape("cylinder")
    m = c.mass(1.0, 1.0)
    assert c.inertia[2] == pytest.approx(m * 0.25 / 2, rel=0.01)
    assert c.inertia[0] == pytest.approx(m * (3 * 0.25 + 1) / 12, rel=0.01)


def test_unknown_shape_is_named():
    with pytest.raises(ValueError, match="unknown shape 'pyramid'"):
        parse_shapes("cube,pyramid")
