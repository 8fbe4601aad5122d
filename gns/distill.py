"""Training against a teacher (train.teacher): a trained model, or an ensemble of them, whose
shape-matched next frames replace some or all of the true ones as targets.

Why: the most accurate MOVi-A predictions come from an ensemble of two long chains (13 h of
training, 0.06x PyBullet's throughput); a fast model trained on the truth learns the
discontinuous contact map from single samples, one trained on the ensemble learns a smoothed,
averaged version of it, from the same windows (docs/accuracy.md, session 23). In pushforward
steps the teacher also answers from the student's own drifted frames, where the true frame is
only a pull back toward the recorded path.

The teacher reads the student's graphs: the same network vertices (mesh, coarse mesh and centre
node), floor and time step. Its mesh edges may differ (surface edges and spokes, or spokes
only): they are rebuilt from the graph's faces (gns.graph.with_surface_edges).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from gns.checkpoint import LATEST, CheckpointError, load_model, read_checkpoint
from gns.graph import GraphBatch, with_surface_edges
from gns.simulator import LearnedSimulator, shape_match_packed


def teacher_paths(setting: str) -> list[Path]:
    """train.teacher "A+B+..." -> the checkpoints (a run folder means its latest.pt)."""
    paths = []
    for part in setting.split("+"):
        path = Path(part.strip())
        paths.append(path / LATEST if path.is_dir() else path)
    return paths


class Teacher:
    """The next frames a trained model (averaged with its ensemble members) predicts, shape-matched
    as its rollouts keep them, on a student's graphs."""

    def __init__(self, setting: str, student: LearnedSimulator, device: torch.device, autocast: str = "auto"):
        self.setting = setting
        models = []
        for path in teacher_paths(setting):
            try:
                models.append(load_model(read_checkpoint(path), device)[0])
            except (CheckpointError, OSError) as e:
                raise CheckpointError(f"train.teacher {path}: {e}") from None
        for k, m in enumerate(models):
            m.set_speed(autocast, False)
            m.requires_grad_(False)
            problem = _mismatch(m, student)
            if problem:
                raise CheckpointError(f"train.teacher {teacher_paths(setting)[k]} cannot teach this model: {problem}")
        self.model, members = models[0], models[1:]
        if members:
            try:
                self.model.set_ensemble(members)
            except ValueError as e:
                raise CheckpointError(f"train.teacher: {e}") from None
        self._rebuild = student._graph_settings["surface_edges"] != self.model._graph_settings["surface_edges"]

    def graph(self, graph: GraphBatch) -> GraphBatch:
        """The student's graph as the teacher reads it (its mesh edges, no collision edges: the
        teacher builds its own from the positions)."""
        if self._rebuild:
            graph = with_surface_edges(graph, self.model._graph_settings["surface_edges"])
        return replace(graph, collision_edges=None)

    @torch.no_grad()
    def next_frame(self, frames: list[torch.Tensor], graph: GraphBatch) -> torch.Tensor:
        """(N, 3) float64: the shape-matched positions at t+1 from frames [..., t-2, t-1, t]."""
        g = self.graph(graph)
        x = self.model.predict_next(*frames[-3:], g)
        return shape_match_packed(x, g.rest, g.node_graph, g.num_graphs)[2]


def _mismatch(teacher: LearnedSimulator, student: LearnedSimulator) -> str:
    """Why `teacher` cannot predict on `student`'s graphs, or ''."""
    mine, theirs = student._graph_settings, teacher._graph_settings
    for key, what in (("max_vertices", "features.mesh_vertices"), ("support_gap", "features.mesh_support_gap"),
                      ("centre_node", "features.centre_node")):
        if mine[key] != theirs[key]:
            return f"{what} is {theirs[key]} there, {mine[key]} here (the network vertices must be the same)"
    if theirs["full_rest"] and not mine["full_rest"]:
        return "it reads the full meshes (features.floor_support), this model's graphs do not carry them"
    if mine["keep_surface"] or theirs["keep_surface"]:
        if (mine["surface_edges"], mine["keep_surface"]) != (theirs["surface_edges"], theirs["keep_surface"]):
            return "features.surface_edge_shapes differs (mixed graphs are not rebuilt)"
    if mine["surface_edges"] != theirs["surface_edges"] and not mine["centre_node"]:
        return "features.surface_edges differs on graphs without a centre node"
    for what, a, b in (("floor height", teacher.layout.floor_z, student.layout.floor_z),
                       ("time step and gravity", teacher.gravity_step, student.gravity_step)):
        if a != b:
            return f"its {what} is {a} there, {b} here"
    return ""
