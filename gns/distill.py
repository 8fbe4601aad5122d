"""Training against a teacher (train.teacher): a trained model, or an ensemble of them, whose
shape-matched next frames replace some or all of the true ones as targets.

Why: the most accurate MOVi-A predictions come from an ensemble of two long chains (13 h of
training, 0.06x PyBullet's throughput); a fast model trained on the truth learns the
discontinuous contact map from single samples, one trained on the ensemble learns a smoothed,
averaged version of it, from the same windows (docs/accuracy.md, session 23). In pushforward
steps the teacher also answers from the student's own drifted frames, where the true frame is
only a pull back toward the recorded path.

The teacher must share the student's floor and time step. On the same network vertices (mesh,
coarse mesh, centre node) it reads the student's graphs, with its own mesh edges where the two
differ in surface edges (rebuilt from the faces: gns.graph.with_surface_edges). On other
vertices (a full-mesh teacher for a coarse student) it packs its own graphs of the batch's
tracks, places them at the poses shape matching finds in the student's frames, and its
predicted pose is placed back on the student's vertices: body frames are the meshes' own, so
augmentations that map them (augment.mirror, augment.body_symmetry) are refused there.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from gns.checkpoint import CheckpointError, checkpoint_of, load_model, read_checkpoint
from gns.data import ObjectTracks
from gns.graph import GraphBatch, with_surface_edges
from gns.rigid import posed, shape_match_packed
from gns.simulator import LearnedSimulator


def teacher_paths(setting: str) -> list[Path]:
    """train.teacher "A+B+..." -> the checkpoints (a run folder means its latest.pt, a bare name a
    shipped model, as `gns eval --run` reads them)."""
    return [checkpoint_of(part.strip()) for part in setting.split("+")]


class Teacher:
    """The next frames a trained model (averaged with its ensemble members) predicts, shape-matched
    as its rollouts keep them, on a student's batches."""

    def __init__(self, setting: str, student: LearnedSimulator, device: torch.device,
                 tracks: ObjectTracks | None = None, meshes: dict | None = None, maps_body_frames: bool = False,
                 autocast: str = "auto", symmetrize: str = ""):
        """tracks, meshes: the student's training tracks and the data's meshes, which a teacher
        on other vertices packs its own graphs from; maps_body_frames: the batches' body frames are
        mapped by augmentation (refused for such a teacher); symmetrize: the teacher's
        predictions averaged over that group's images (train.teacher_symmetrize)."""
        paths = teacher_paths(setting)
        models = []
        for path in paths:
            try:
                models.append(load_model(read_checkpoint(path), device)[0])
            except (CheckpointError, OSError) as e:
                raise CheckpointError(f"train.teacher {path}: {e}") from None
        self.library = None
        for k, m in enumerate(models):
            m.set_speed(autocast, False)
            m.requires_grad_(False)
            problem = _mismatch(m, student)
            if not problem and k == 0 and _other_vertices(m, student):
                if tracks is None or meshes is None:
                    problem = "it reads other network vertices, and no training tracks were given to pack its graphs"
                elif maps_body_frames:
                    problem = ("it reads other network vertices, which cannot follow augment.mirror or "
                               "augment.body_symmetry (they map the body frames)")
                else:
                    self.library = m.mesh_library(meshes)
            if problem:
                raise CheckpointError(f"train.teacher {paths[k]} cannot teach this model: {problem}")
        self.model, members = models[0], models[1:]
        self.model.symmetrize = symmetrize or False   # the members follow the first model's setting
        if members:
            try:
                self.model.set_ensemble(members)
            except ValueError as e:
                raise CheckpointError(f"train.teacher: {e}") from None
        if self.library is not None:
            names = [tracks.library.names[i] for i in tracks.shape_ids.tolist()]
            self._tracks = (self.library.shape_ids(names), tracks.scale, tracks.friction, tracks.restitution)
        self._rebuild = student._graph_settings["surface_edges"] != self.model._graph_settings["surface_edges"]

    def graph(self, graph: GraphBatch) -> GraphBatch:
        """The student's graph as a teacher on the same vertices reads it (its mesh edges, no
        collision edges: the teacher builds its own from the positions)."""
        if self._rebuild:
            graph = with_surface_edges(graph, self.model._graph_settings["surface_edges"])
        return replace(graph, collision_edges=None)

    @torch.no_grad()
    def next_frame(self, frames: list[torch.Tensor], graph: GraphBatch,
                   tracks: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 3) float64: the shape-matched positions at t+1 from frames [..., t-2, t-1, t] of
        the student's graph; `tracks` (G,): each graph's track (Batch.tracks), for a teacher on
        other vertices."""
        if self.library is None:
            g = self.graph(graph)
            x = self.model.predict_next(*frames[-3:], g)
            return shape_match_packed(x, g.rest, g.node_graph, g.num_graphs)[2]
        if tracks is None:
            raise ValueError("a teacher on other vertices needs each graph's track (Batch.tracks)")
        shape, scale, friction, restitution = (t[tracks.cpu()] for t in self._tracks)
        own = self.library.pack(shape, scale, friction, restitution, graph.graph_scene).to(graph.rest.device)
        placed = []
        for x in frames[-3:]:
            rot, centre, _ = shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)
            placed.append(posed(rot, centre, own.node_graph, own.rest))
        x = self.model.predict_next(*placed, own)
        rot, centre, _ = shape_match_packed(x, own.rest, own.node_graph, own.num_graphs)
        return posed(rot, centre, graph.node_graph, graph.rest)



def _other_vertices(teacher: LearnedSimulator, student: LearnedSimulator) -> bool:
    return any(teacher._graph_settings[k] != student._graph_settings[k]
               for k in ("max_vertices", "support_gap", "centre_node"))


def _mismatch(teacher: LearnedSimulator, student: LearnedSimulator) -> str:
    """Why `teacher` cannot predict on `student`'s graphs, or ''."""
    mine, theirs = student._graph_settings, teacher._graph_settings
    if not _other_vertices(teacher, student):   # it reads the student's own graphs
        if theirs["full_rest"] and not mine["full_rest"]:
            return "it reads the full meshes (features.floor_support), this model's graphs do not carry them"
        if (mine["keep_surface"] or theirs["keep_surface"]) and \
                (mine["surface_edges"], mine["keep_surface"]) != (theirs["surface_edges"], theirs["keep_surface"]):
            return "features.surface_edge_shapes differs (mixed graphs are not rebuilt)"
    for what, a, b in (("floor height", teacher.layout.floor_z, student.layout.floor_z),
                       ("time step and gravity", teacher.gravity_step, student.gravity_step)):
        if a != b:
            return f"its {what} is {a} there, {b} here"
    return ""
