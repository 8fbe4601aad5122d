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
        support        (N, 4)  offset to the object's full-mesh low point, and that point's
                               floor distance (features.floor_support; made by the
                               simulator, which shape-matches each object's pose first)
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

from gns import parallel
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
        stats = parallel.sum_over_processes(torch.cat([x.sum(0), (x * x).sum(0), x.new_full((1,), x.shape[0])]))
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
    velocity_scale: float = 0.0      # "velocity_direction": v / (|v| + velocity_scale), scene units per frame
    floor_signed: bool = False       # the floor distance keeps its sign below the floor (to -floor_clip)
    gravity_z_step: float = 0.0      # "impact": gravity's z component times dt^2, scene units per frame^2

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


def make_layout(features_cfg, floor_z: float | None, materials_vary: bool, collisions: bool = False,
                gravity_step: float | None = None, gravity_z_step: float | None = None) -> FeatureLayout:
    """features_cfg: a FeatureConfig. floor_z None when the dataset has no floor; collisions
    when it has scenes of several objects; gravity_step |g| dt^2 (scene units per frame), which
    features.velocity_direction is measured in (needs a dataset with gravity); gravity_z_step its
    z component (features.impact_time)."""
    f = features_cfg
    node = []
    if f.velocity:
        node.append(("velocity", 3 * (HISTORY - 1)))
    velocity_scale = 0.0
    if f.velocity_direction > 0:
        if not gravity_step:
            raise ConfigError("features.velocity_direction needs a dataset with gravity")
        velocity_scale = f.velocity_direction * gravity_step
        node.append(("velocity_direction", 3 * (HISTORY - 1)))
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
        if getattr(f, "edge_velocity", False):
            edge.append(("relative_velocity", 3))   # last: fine-tuning may add it (see "impact")
    impact = bool(getattr(f, "impact_time", False))
    if impact:
        if floor_z is None or not f.floor_distance:
            raise ConfigError("features.impact_time needs a dataset with a floor and features.floor_distance")
        if gravity_z_step is None:
            raise ConfigError("features.impact_time needs a dataset with gravity")
        # last, so that a model trained without it can be fine-tuned with it (gns.train widens
        # the node encoder's first layer by a zero column: the start computes what it did)
        node.append(("impact", 1))
    if getattr(f, "floor_support", False):
        if floor_z is None:
            raise ConfigError("features.floor_support needs a dataset with a floor")
        node.append(("support", 4))   # last, for the same reason as "impact"
    if not node:
        raise ConfigError("no node features are on: switch on features.velocity or features.rest_position")
    collision = (("collision_relative", 3), ("collision_relative_norm", 1)) if collisions else ()
    return FeatureLayout(tuple(node), tuple(edge), floor_z if f.floor_distance else None, f.floor_clip,
                         collision, float(f.collision_radius), velocity_scale, bool(f.floor_signed),
                         float(gravity_z_step or 0.0) if impact else 0.0)


def raw_node_features(layout: FeatureLayout, history: torch.Tensor, graph: GraphBatch) -> dict[str, torch.Tensor]:
    """history (N, 3, 3) float64 positions at t-2, t-1, t -> {group: (N, width) float32}."""
    out = {}
    x_t = history[:, -1]
    for name, _ in layout.node_groups:
        if name == "velocity":
            v = history[:, 1:] - history[:, :-1]                 # (N, 2, 3): older first
            out[name] = v.flip(1).reshape(len(history), 3 * (HISTORY - 1))  # newest first
        elif name == "velocity_direction":
            # Coulomb friction flips with the sign of a slow sliding velocity; normalised by the
            # spread of flight speeds, such velocities are too small for the MLP to resolve, so
            # it learns a friction that fades out before the object stops. The direction is
            # resolved at any speed above velocity_scale.
            v = (history[:, 1:] - history[:, :-1]).flip(1)
            out[name] = (v / (v.norm(dim=-1, keepdim=True) + layout.velocity_scale)).reshape(len(history), -1)
        elif name == "floor":
            low = -layout.floor_clip if layout.floor_signed else 0.0
            out[name] = (x_t[:, 2:3] - layout.floor_z).clamp(low, layout.floor_clip)
        elif name == "impact":
            out[name] = impact_share(x_t[:, 2:3] - layout.floor_z, history[:, -2, 2:3] - layout.floor_z,
                                     layout.gravity_z_step)
        elif name == "material":
            out[name] = graph.material
        elif name == "rest_position":
            out[name] = graph.rest
        elif name == "position":
            out[name] = x_t
    return {k: v.to(torch.float32) for k, v in out.items()}


# the low point is the centroid of the full mesh's vertices weighted by exp(-height above the
# lowest / (SUPPORT_SHARPNESS x size)): a face lying flat gives its centre, not whichever of its
# corners is lowest by round-off, and the point moves continuously as the object tips
SUPPORT_SHARPNESS = 0.01


def floor_support(layout: FeatureLayout, x_t: torch.Tensor, graph: GraphBatch, rot: torch.Tensor,
                  centre: torch.Tensor) -> torch.Tensor:
    """The "support" node feature (N, 4) float64: per node, the offset from it to its object's
    full-mesh low point (graph.full_rest placed at the pose rot (G, 3, 3), centre (G, 3)), and
    that point's floor distance, clipped as the floor feature is."""
    if graph.full_rest is None:
        raise ValueError("features.floor_support needs graphs with full_rest (MeshLibrary(..., full_rest=True))")
    world = graph.full_rest @ rot.transpose(1, 2) + centre[:, None]            # (G, V, 3), NaN rows: padding
    z = torch.nan_to_num(world[..., 2], nan=torch.inf)
    low = z.amin(dim=1)
    rest = graph.full_rest.nan_to_num(0)   # a padding row at 0 (the centre) widens no box
    size = (rest.amax(1) - rest.amin(1)).amax(1)
    weight = torch.softmax(-(z - low[:, None]) / (SUPPORT_SHARPNESS * size[:, None]), dim=1)
    point = (weight[..., None] * world.nan_to_num(0)).sum(1)                   # (G, 3)
    floor = -layout.floor_clip if layout.floor_signed else 0.0
    height = (low - layout.floor_z).clamp(floor, layout.floor_clip)
    return torch.cat([point[graph.node_graph] - x_t, height[graph.node_graph, None]], dim=1)


def impact_share(z_t: torch.Tensor, z_tm1: torch.Tensor, g_z: float) -> torch.Tensor:
    """The share of the step t -> t+1 a vertex at height z_t (z_tm1 a frame before; heights above
    the floor) spends below the floor if it moves on ballistically: 1 - (time of impact / dt),
    with the time of impact interpolated linearly between z_t and the ballistic next height
    2 z_t - z_tm1 + g_z. 0 without an impact in the step, 1 for a vertex already below."""
    z_next = 2 * z_t - z_tm1 + g_z
    crossing = (z_t > 0) & (z_next < 0)
    share = torch.where(crossing, -z_next / torch.where(crossing, z_t - z_next, torch.ones_like(z_t)),
                        torch.zeros_like(z_t))
    return torch.where(z_t <= 0, torch.ones_like(z_t), share)


def raw_edge_features(layout: FeatureLayout, history: torch.Tensor, graph: GraphBatch) -> dict[str, torch.Tensor]:
    """history (N, 3, 3) float64 -> {group: (E, width) float32} for the mesh edges."""
    s, r = graph.mesh_edges.senders, graph.mesh_edges.receivers
    out = {}
    names = {name for name, _ in layout.edge_groups}
    if "relative" in names:
        x_t = history[:, -1]
        d = x_t[r] - x_t[s]
        out["relative"], out["relative_norm"] = d, d.norm(dim=-1, keepdim=True)
    if "relative_velocity" in names:
        x_t, x_tm1 = history[:, -1], history[:, -2]
        out["relative_velocity"] = (x_t[r] - x_t[s]) - (x_tm1[r] - x_tm1[s])
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
