"""Unit rigid assets: convex, watertight meshes spanning +-0.5, centred on their centre of mass.

The vertex counts follow the paper's meshes (Kubric's VHACD hulls have 51-64 vertices),
except `cube`, which is the plain 8-vertex cube of the real-cube data. The rest vertices and
faces are written into every shard so a model sees exactly the shape that was simulated.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import trimesh

SHAPES = ("cube", "beveled_cube", "cylinder", "sphere")


@dataclass(frozen=True)
class Shape:
    name: str
    vertices: np.ndarray  # (V, 3) float64, unit asset, centre of mass at the origin
    faces: np.ndarray     # (F, 3) int32, outward-oriented triangles
    volume: float         # of the unit asset
    inertia: np.ndarray   # (3,) principal moments of the unit asset at density 1

    def mass(self, density: float, scale: float) -> float:
        return density * self.volume * scale**3

    def inertia_diagonal(self, density: float, scale: float) -> np.ndarray:
        # Mass scales with s^3 and the squared lever arm with s^2.
        return density * self.inertia * scale**5


def _beveled_cube_points() -> np.ndarray:
    # Minkowski sum of a cube of half-width 0.45 and a sphere of radius 0.05 (Kubric's bevel),
    # sampled with 7 directions per corner octant: 3 face normals, 3 edge bisectors, 1 diagonal.
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 1, 1]], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                sign = np.array([sx, sy, sz], float)
                pts.append(sign * (0.45 + 0.05 * dirs))
    return np.concatenate(pts)


def _cylinder_points(sections: int = 32) -> np.ndarray:
    ang = 2 * np.pi * np.arange(sections) / sections
    ring = np.stack([0.5 * np.cos(ang), 0.5 * np.sin(ang)], axis=1)
    top = np.column_stack([ring, np.full(sections, 0.5)])
    bottom = np.column_stack([ring, np.full(sections, -0.5)])
    return np.concatenate([top, bottom])


def _sphere_points() -> np.ndarray:
    # Poles plus 5 latitude rings of 12: the equator ring and the poles reach +-0.5 on every axis.
    pts = [[0, 0, 0.5], [0, 0, -0.5]]
    for lat in np.radians([-60, -30, 0, 30, 60]):
        for lon in np.radians(np.arange(0, 360, 30)):
            pts.append([0.5 * np.cos(lat) * np.cos(lon), 0.5 * np.cos(lat) * np.sin(lon), 0.5 * np.sin(lat)])
    return np.array(pts)


def _cube_points() -> np.ndarray:
    return np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], float)


_BUILDERS = {
    "cube": _cube_points,
    "beveled_cube": _beveled_cube_points,
    "cylinder": _cylinder_points,
    "sphere": _sphere_points,
}


@lru_cache(maxsize=None)
def get_shape(name: str) -> Shape:
    if name not in _BUILDERS:
        raise ValueError(f"unknown shape {name!r}; known shapes: {', '.join(SHAPES)}")
    hull = trimesh.convex.convex_hull(_BUILDERS[name]())
    # Symmetric by construction; recentring guards against round-off only.
    hull.apply_translation(-hull.center_mass)
    tensor = hull.moment_inertia  # at density 1
    off_diag = np.abs(tensor - np.diag(np.diag(tensor))).max()
    if off_diag > 1e-9 * np.abs(tensor).max():
        raise AssertionError(f"{name}: body axes are not principal axes (off-diagonal {off_diag:g})")
    return Shape(
        name=name,
        vertices=np.asarray(hull.vertices, dtype=np.float64),
        faces=np.asarray(hull.faces, dtype=np.int32),
        volume=float(hull.volume),
        inertia=np.diag(tensor).copy(),
    )


def parse_shapes(text: str | list[str]) -> list[str]:
    names = [s.strip() for s in (text.split(",") if isinstance(text, str) else text) if s.strip()]
    if not names:
        raise ValueError("no shapes given")
    for n in names:
        if n not in _BUILDERS:
            raise ValueError(f"unknown shape {n!r}; known shapes: {', '.join(SHAPES)}")
    return names
