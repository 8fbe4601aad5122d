"""Node and edge features of a mesh graph, and the running normalisers that scale them.

Features are computed from float64 positions and cast to float32 only after differencing, so
that a scene far from the origin loses no precision (translation equivariance holds to float32
round-off of the differences, not of the absolute coordinates).

Feature groups (each normalised separately, each switchable in [features]):
  node  velocity       (N, 6)  x_t - x_{t-1}, x_{t-1} - x_{t-2}
        floor          (N, 1)  clip(z_t - floor_z, 0, floor_clip) (from -floor_clip with
                               floor_signed); only if the data has a floor
        material       (N, 2)  friction, restitution; only if the data's materials vary
        rest_position  (N, 3)  scaled rest vertex in the body frame
        position       (N, 3)  x_t; absolute encoding only
  edge  relative       (E, 3)  d = x_r - x_s (receiver minus sender), and |d| (E, 1)
        rest_relative  (E, 3)  d^U = rest_r - rest_s, and |d^U| (E, 1)
  With the absolute encoding edges get one constant zero input (E, 1), unnormalised.
  collision  collision_relative (C, 3)  d = x_r - x_s across two objects, and |d| (C, 1);
        only when the dataset has multi-object scenes (ModelSpec.collision_edges); no rest-shape
        features (meaningless across objects); the same with either encoding.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from gns import hardware
from gns.config import ConfigError
from gns.graph import GraphBatch

STD_EPSILON = 1e-5
HISTORY = 3  # input frames t-2, t-1, t: two finite-difference velocities (paper: h = 2)


class Normalizer(nn.Module):
    """Running mean/std of a feature group, accumulated online and kept in the state_dict.

    Statistics accumulate (in float64) on every call with `accumulate=True` until
    `max_accumulations` calls; mean and std are then frozen. std is floored at STD_EPSILON so a
    constant feature does not blow up.
    """

    def __init__(self, size: int, max_accumulations: int):
        super().__init__()
        self.max_accumulations = max_accumulations
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("accumulations", torch.zeros((), dtype=torch.int64))
        self.register_buffer("sum", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("sum_squared", torch.zeros(size, dtype=torch.float64))

    def accumulate(self, x: torch.Tensor) -> None:
        """x (M, size). Adds its rows to the statistics unless the budget of calls is spent."""
        if int(self.accumulations) >= self.max_accumulations:
            return
        x = x.detach().to(torch.float64)
        size = self.sum.shape[0]
        # one vector, summed over the processes of a multi-process run, so that every process
        # holds the statistics of the whole global batch (identical to one process training it)
        stats = hardware.sum_over_processes(torch.cat([x.sum(0), (x * x).sum(0), x.new_full((1,), x.shape[0])]))
        if stats[-1] == 0:
            return
        self.count += stats[-1]
        self.sum += stats[:size]
        self.sum_squared += stats[size:2 * size]
        self.accumulations += 1

    @property
    def mean(self) -> torch.Tensor:
        return self.sum / self.count.clamp(min=1.0)

    @property
    def std(self) -> torch.Tensor:
        var = self.sum_squared / self.count.clamp(min=1.0) - self.mean ** 2
        return var.clamp(min=0.0).sqrt().clamp(min=STD_EPSILON)

    def forward(self, x: torch.Tensor, accumulate: bool = False) -> torch.Tensor:
        if accumulate:
            self.accumulate(x)
        return ((x - self.mean.to(x.dtype)) / self.std.to(x.dtype))

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        return y * self.std.to(y.dtype) + self.mean.to(y.dtype)


@dataclass(frozen=True)
class FeatureLayout:
    """Which groups are on, decided once from the config and the dataset, with their widths."""

    node_groups: tuple[tuple[str, int], ...]
    edge_groups: tuple[tuple[str, int], ...]
    floor_z: float | None
    floor_clip: float
    collision_groups: tuple[tuple[str, int], ...] = ()
    collision_radius: float = 0.0
    floor_signed: bool = False       # the floor distance keeps its sign below the floor (to -floor_clip)

    @property
    def collisions(self) -> bool:
        return bool(self.collision_groups)

    @property
    def collision_size(self) -> int:
        return sum(w for _, w in self.collision_groups)

    @property
    def node_size(self) -> int:
        return sum(w for _, w in self.node_groups)

    @property
    def edge_size(self) -> int:
        return sum(w for _, w in self.edge_groups) or 1

    @property
    def absolute(self) -> bool:
        return not self.edge_groups


def make_layout(features_cfg, floor_z: float | None, materials_vary: bool, collisions: bool = False) -> FeatureLayout:
    """features_cfg: a FeatureConfig. floor_z None when the dataset has no floor; collisions
    when it has scenes of several objects."""
    f = features_cfg
    node = []
    if f.velocity:
        node.append(("velocity", 3 * (HISTORY - 1)))
    if f.floor_distance and floor_z is not None:
        node.append(("floor", 1))
    if f.material and materials_vary:
        node.append(("material", 2))
    absolute = f.encoding == "absolute"
    # The absolute encoding gives nodes x and x^U (paper, GNS [abs]) whatever rest_position says.
    if f.rest_position or absolute:
        node.append(("rest_position", 3))
    edge = []
    if absolute:
        node.append(("position", 3))
    else:
        edge += [("relative", 3), ("relative_norm", 1)]
        if f.rest_edges:
            edge += [("rest_relative", 3), ("rest_relative_norm", 1)]
    if not node:
        raise ConfigError("no node features are on: switch on features.velocity or features.rest_position")
    collision = (("collision_relative", 3), ("collision_relative_norm", 1)) if collisions else ()
    return FeatureLayout(tuple(node), tuple(edge), floor_z if f.floor_distance else None, f.floor_clip,
                         collision, float(f.collision_radius), bool(f.floor_signed))


def raw_node_features(layout: FeatureLayout, history: torch.Tensor, graph: GraphBatch) -> dict[str, torch.Tensor]:
    """history (N, 3, 3) float64 positions at t-2, t-1, t -> {group: (N, width) float32}."""
    out = {}
    x_t = history[:, -1]
    for name, _ in layout.node_groups:
        if name == "velocity":
            v = history[:, 1:] - history[:, :-1]                 # (N, 2, 3): older first
            out[name] = v.flip(1).reshape(len(history), 3 * (HISTORY - 1))  # newest first
        elif name == "floor":
            low = -layout.floor_clip if layout.floor_signed else 0.0
            out[name] = (x_t[:, 2:3] - layout.floor_z).clamp(low, layout.floor_clip)
        elif name == "material":
            out[name] = graph.material
        elif name == "rest_position":
            out[name] = graph.rest
        elif name == "position":
            out[name] = x_t
    return {k: v.to(torch.float32) for k, v in out.items()}


def raw_edge_features(layout: FeatureLayout, history: torch.Tensor, graph: GraphBatch) -> dict[str, torch.Tensor]:
    """history (N, 3, 3) float64 -> {group: (E, width) float32} for the mesh edges."""
    s, r = graph.mesh_edges.senders, graph.mesh_edges.receivers
    out = {}
    names = {name for name, _ in layout.edge_groups}
    if "relative" in names:
        x_t = history[:, -1]
        d = x_t[r] - x_t[s]
        out["relative"], out["relative_norm"] = d, d.norm(dim=-1, keepdim=True)
    if "rest_relative" in names:
        d = graph.rest[r] - graph.rest[s]
        out["rest_relative"], out["rest_relative_norm"] = d, d.norm(dim=-1, keepdim=True)
    return {k: v.to(torch.float32) for k, v in out.items()}


def raw_collision_features(history: torch.Tensor, edges) -> dict[str, torch.Tensor]:
    """history (N, 3, 3) float64, collision edges s -> r (a gns.graph.EdgeSet) -> {group:
    (C, width) float32}: d = x_r - x_s and |d|, or for surface edges (gns.contacts) the vertex
    minus its closest surface point and the signed distance, in the same two groups."""
    if edges.vectors is not None:
        return {"collision_relative": edges.vectors.to(torch.float32),
                "collision_relative_norm": edges.signed.to(torch.float32)}
    x_t = history[:, -1]
    d = x_t[edges.receivers] - x_t[edges.senders]
    return {"collision_relative": d.to(torch.float32),
            "collision_relative_norm": d.norm(dim=-1, keepdim=True).to(torch.float32)}
