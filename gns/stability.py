"""Stability at the extremes: what a simulator does where users push it.

Three kinds of check, each returning plain dicts for a report (pipelines/stability.py) or a test:
- long rollouts: scenes rolled out far past the length the model was trained on: finite,
  rigid, centres above the floor (objects do not fall through), deepest floor penetration;
- at rest: an object resting on the floor, rolled out for many steps: its centre's drift;
- extreme inputs: the test scenes changed one way at a time (3x speeds, friction and
  restitution at 0 and 1, sizes 0.01x and 100x, 1e4 units from the origin, float32 arrays).
  Each must be either handled (a rollout that is finite and, where an exact answer exists,
  equal to it) or named by the range check (gns.spec.outside_training) as outside training.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from datagen.shards import Scene
from gns.data import ObjectTracks, feature_spec
from gns.network import HISTORY
from gns.graph import MeshLibrary, graph_centres, graph_sizes, per_graph
from gns.spec import outside_training
from gns.simulator import LearnedSimulator
from gns.spec import ModelSpec

# Criteria. Rigidity: shape matching makes every predicted frame an exact rigid pose, so any
# distortion beyond float64 rounding is a bug. At rest: the 0.1% of the size over 1000
# steps. Handled: a shifted or float32 rollout within 0.1% of the size of the original.
RIGID_PCT = 1e-6
REST_DRIFT_PCT = 0.1
SAME_PCT = 0.1


@torch.no_grad()
def _roll(sim: LearnedSimulator, scenes: list[Scene], library: MeshLibrary, steps: int, sleep: bool | None = None):
    """Rollout of every object of `scenes` from its first 3 frames: (graph, given vertices
    (N, 3, 3), predicted vertices (steps, N, 3), sizes (G,)); `sleep` (None: as sim.options say)."""
    tracks = ObjectTracks(scenes, library, name="stability scenes")
    graph, verts, _ = tracks.track_vertices(torch.arange(tracks.num_tracks), HISTORY)
    with sim.using(sleep=sleep):
        pred = sim.rollout(verts, graph, steps)
    return graph, verts, pred, graph_sizes(graph)


def _per_graph(values: torch.Tensor, graph, reduce: str, owner: torch.Tensor | None = None) -> torch.Tensor:
    """Reduce node (or, with their `owner` graphs, edge) values per step (S, N) to graphs (S, G)."""
    return per_graph(values.T, graph, reduce, owner).T


def long_rollouts(sim: LearnedSimulator, scenes: list[Scene], meshes: dict, floor_z: float | None,
                  factor: int = 10) -> dict:
    """Roll the scenes out `factor` times their length. Distortion is the largest change of a
    mesh edge's length (% of the object's size); penetration the deepest vertex below the floor."""
    steps = factor * max(sc.num_frames for sc in scenes)
    graph, _, pred, size = _roll(sim, scenes, sim.mesh_library(meshes), steps)
    s, r = graph.mesh_edges.senders, graph.mesh_edges.receivers
    rest_len = (graph.rest[s] - graph.rest[r]).norm(dim=-1)
    distortion = ((pred[:, s] - pred[:, r]).norm(dim=-1) - rest_len).abs()
    distortion_pct = float((_per_graph(distortion, graph, "amax", graph.node_graph[s]) / size * 100).max())
    # a scene is finite when every coordinate of every object stays finite at every step
    bad_nodes = (~torch.isfinite(pred).all(-1).all(0)).double()                        # (N,)
    bad = torch.zeros(len(scenes), dtype=torch.float64).index_add_(0, graph.graph_scene[graph.node_graph], bad_nodes)
    scenes_finite = bad == 0
    out = {"steps": steps, "objects": graph.num_graphs, "scenes": len(scenes),
           "finite_scenes_pct": float(scenes_finite.double().mean() * 100), "finite": bool(torch.isfinite(pred).all()),
           "distortion_pct": distortion_pct, "rigid": distortion_pct < RIGID_PCT}
    if floor_z is not None:
        depth = _per_graph(floor_z - pred[..., 2], graph, "amax").clamp(min=0) / size * 100
        centre_z = torch.stack([graph_centres(x, graph)[:, 2] for x in pred])
        out.update(max_penetration_pct=float(depth.max()), mean_penetration_pct=float(depth.mean()),
                   min_centre_height=float(centre_z.min() - floor_z), above_floor=bool((centre_z > floor_z).all()))
    return out


def resting_scene(shape: str, scale: float, meshes: dict, floor_z: float, frames: int = HISTORY + 1,
                  friction: float = 0.5, restitution: float = 0.5) -> Scene:
    """One object lying still on the floor (lowest vertex touching it), unrotated."""
    rest = np.asarray(meshes[shape][0]) * scale
    pos = np.zeros((frames, 1, 3))
    pos[..., 2] = floor_z - rest[:, 2].min()
    zeros = np.zeros((frames, 1, 3))
    return Scene(pos, np.tile([1.0, 0.0, 0.0, 0.0], (frames, 1, 1)), zeros, zeros.copy(), [shape], ["rest"],
                 np.array([scale]), np.array([1.0]), np.array([friction]), np.array([restitution]))


def at_rest(sim: LearnedSimulator, scenes: list[Scene], meshes: dict, steps: int = 1000,
            sleep: bool | None = None) -> list[dict]:
    """Drift of each resting scene's object centre after `steps` (% of its size); `sleep`: with
    resting objects deactivated (None: as sim.options say)."""
    graph, given, pred, size = _roll(sim, scenes, sim.mesh_library(meshes), steps, sleep)
    centre = torch.stack([graph_centres(pred[k], graph) for k in (0, steps // 10 - 1, steps - 1)])
    start = graph_centres(given[:, -1], graph)
    drift = (centre - start).norm(dim=-1) / size * 100
    return [{"shape": sc.shape[0], "scale": float(sc.scale[0]), "steps": steps,
             f"drift_pct_after_{steps // 10}": float(drift[1, i]), "drift_pct": float(drift[2, i]),
             "passed": bool(drift[2, i] < REST_DRIFT_PCT)} for i, sc in enumerate(scenes)]


def _changed(sc: Scene, **arrays) -> Scene:
    return dataclasses.replace(sc, **arrays)


def _faster(sc: Scene, k: float) -> Scene:
    """A toss k times as fast across the floor: horizontal displacements from the first frame
    times k, heights unchanged (a faster fall would go below the floor). Only the 3 given
    frames drive a rollout; the rest set the speed range the check sees."""
    positions = sc.positions.copy()
    positions[..., :2] = sc.positions[:1, :, :2] + k * (sc.positions[..., :2] - sc.positions[:1, :, :2])
    velocities = sc.velocities.copy()
    velocities[..., :2] *= k
    return _changed(sc, positions=positions, velocities=velocities)


def extreme_variants(offset: float = 1e4) -> dict:
    """name -> function(scene) -> scene: one extreme at a time."""
    shift = np.array([offset, offset, 0.0]) / np.sqrt(2)
    return {
        "3x speed": lambda sc: _faster(sc, 3.0),
        "friction 0": lambda sc: _changed(sc, friction=np.zeros_like(sc.friction)),
        "friction 1": lambda sc: _changed(sc, friction=np.ones_like(sc.friction)),
        "restitution 0": lambda sc: _changed(sc, restitution=np.zeros_like(sc.restitution)),
        "restitution 1": lambda sc: _changed(sc, restitution=np.ones_like(sc.restitution)),
        "size 0.01x": lambda sc: _changed(sc, scale=sc.scale * 0.01, positions=sc.positions * 0.01,
                                          velocities=sc.velocities * 0.01),
        "size 100x": lambda sc: _changed(sc, scale=sc.scale * 100, positions=sc.positions * 100,
                                         velocities=sc.velocities * 100),
        f"{offset:g} units from the origin": lambda sc: _changed(sc, positions=sc.positions + shift),
        "float32 arrays": lambda sc: _changed(sc, **{k: getattr(sc, k).astype(np.float32) for k in
                                                    ("positions", "quaternions", "velocities", "angular_velocities")}),
    }


class _DatasetView:
    """What feature_spec reads of a dataset, for scenes changed in memory."""

    def __init__(self, ds):
        self.frame_rate, self.gravity, self.floor, self.materials_vary = \
            ds.frame_rate, ds.gravity, ds.floor, ds.materials_vary


def extremes(sim: LearnedSimulator, trained_spec: ModelSpec, scenes: list[Scene], ds, steps: int | None = None) -> list[dict]:
    """Each extreme variant of `scenes`: the range check's warnings, and whether the rollout is
    finite and (for a shift or a float32 copy, whose exact answer is the original rollout
    shifted or unchanged) equal to the original within SAME_PCT of the object size."""
    steps = steps or max(sc.num_frames for sc in scenes) - HISTORY
    library = sim.mesh_library(ds.meshes)
    _, _, base, size = _roll(sim, scenes, library, steps)
    rows = []
    for name, change in extreme_variants().items():
        changed = [change(sc) for sc in scenes]
        warnings = outside_training(trained_spec, feature_spec(_DatasetView(ds), changed))
        graph, _, pred, _ = _roll(sim, changed, library, steps)
        row = {"case": name, "warnings": warnings, "finite": bool(torch.isfinite(pred).all())}
        if "origin" in name or "float32" in name:
            shift = torch.from_numpy(changed[0].positions[0, 0] - scenes[0].positions[0, 0]).to(pred.dtype)
            diff = _per_graph((pred - shift - base).norm(dim=-1), graph, "amax") / size * 100
            row["difference_pct"] = float(diff.max())
            row["handled"] = row["finite"] and row["difference_pct"] < SAME_PCT
        else:
            row["handled"] = False
        row["passed"] = row["handled"] or bool(warnings)
        rows.append(row)
    return rows
