"""The network and what it reads: an encode-process-decode graph network on an already built,
normalised graph, and (further down) the node and edge features of a mesh graph with their
running normalisers.

Message passing convention (pinned by tests/test_gns_network.py):
- An edge k goes from node s = senders[k] to node r = receivers[k]. In the paper's notation
  E_ij with i = r (the node that is updated) and j = s (its neighbour).
- Edge update: m_k = f_E(E_k, V_r, V_s), inputs concatenated in that order.
- Node update: V'_r = V_r + f_V(V_r, sum_{k: receivers[k] = r} m_k). A node sums the new
  messages m_k, i.e. the edge update *before* the edge residual is added, as DeepMind's
  InteractionNetwork (graph_nets / jraph) does.
- Edge residual: E'_k = E_k + m_k; the next block sees E'.
- The processor holds L blocks with unshared weights and applies the sequence K times.
- Edge sets are a list, mesh edges first; each has its own encoder and per-block edge function
  (as MeshGraphNets' mesh and world edges), and a block loops over them:
  V'_r = V_r + f_V(V_r, sum of set 1's messages, sum of set 2's, ...), E'_k = E_k + m_k per set.
  The optional second set is the collision edges between objects (c_k = f_C(C_k, V_r, V_s)); a
  network built without it (collision_edge_in = 0) has none of its parameters.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn

from gns.config import ConfigError
from gns.graph import GraphBatch


class MLP(nn.Sequential):
    """`hidden_layers` ReLU layers of width `hidden`, a linear output, optionally a LayerNorm."""

    def __init__(self, in_size: int, hidden: int, hidden_layers: int, out_size: int, layer_norm: bool):
        sizes = [in_size] + [hidden] * hidden_layers
        layers: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(a, b), nn.ReLU()]
        layers.append(nn.Linear(sizes[-1], out_size))
        if layer_norm:
            layers.append(nn.LayerNorm(out_size))
        super().__init__(*layers)


def _add_edge_function(module: nn.Module, latent: int, hidden: int, hidden_layers: int, layer_norm: bool) -> None:
    """Give `module` the layers of f_E(E, V_r, V_s): an MLP whose first layer is split into
    edge_in (on E), receiver_in (on V_r) and sender_in (on V_s), then edge_rest."""
    first = hidden if hidden_layers > 0 else latent
    module.edge_in = nn.Linear(latent, first)
    module.receiver_in = nn.Linear(latent, first, bias=False)
    module.sender_in = nn.Linear(latent, first, bias=False)
    rest: list[nn.Module] = []
    if hidden_layers > 0:
        rest.append(nn.ReLU())
        rest.extend(MLP(hidden, hidden, hidden_layers - 1, latent, layer_norm))
    elif layer_norm:
        rest.append(nn.LayerNorm(latent))
    module.edge_rest = nn.Sequential(*rest)


def _edge_messages(module: nn.Module, nodes, edges, senders, receivers, per_node: bool = True) -> torch.Tensor:
    # per_node: the node parts of the first layer are applied once per node, then gathered per
    # edge: equal to the concatenated form but O(N) instead of O(E), for mesh edges (E ~ 2N).
    # Collision edges are fewer than nodes (a vertex has at most one from each other object, most
    # have none): there the nodes are gathered first and the layer applied per edge. index_select
    # is the gather x[idx]; its backward (index_add_) is about twice as fast on CPU.
    if per_node:
        return module.edge_rest(module.edge_in(edges) + module.receiver_in(nodes).index_select(0, receivers)
                                + module.sender_in(nodes).index_select(0, senders))
    return module.edge_rest(module.edge_in(edges) + module.receiver_in(nodes.index_select(0, receivers))
                            + module.sender_in(nodes.index_select(0, senders)))


EdgeLatents = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # edges (E, D), senders (E,), receivers (E,)


class InteractionBlock(nn.Module):
    """One message-passing update with residuals on nodes and edges (see the module docstring).

    The first layer of f_E acts on [E, V_r, V_s], split per part (_edge_messages). The mesh
    edges' function lives on the block itself and the collision edges' in `self.collision`, so
    checkpoints keep their parameter names.
    """

    def __init__(self, latent: int, hidden: int, hidden_layers: int, layer_norm: bool = True,
                 collisions: bool = False):
        super().__init__()
        _add_edge_function(self, latent, hidden, hidden_layers, layer_norm)
        self.collision = EdgeFunction(latent, hidden, hidden_layers, layer_norm) if collisions else None
        self.node_mlp = MLP((3 if collisions else 2) * latent, hidden, hidden_layers, latent, layer_norm)

    def edge_functions(self) -> list[nn.Module]:
        """One module per edge set, in the order of the edge sets: mesh, then collision."""
        return [self] if self.collision is None else [self, self.collision]

    def forward(self, nodes: torch.Tensor, edge_sets: list[EdgeLatents]) -> tuple[torch.Tensor, list[EdgeLatents]]:
        """nodes (N, D), one (edges, senders, receivers) per edge function -> new nodes (N, D)
        and the edge sets with their new edge latents."""
        summed, updated = [], []
        for k, (function, (edges, senders, receivers)) in enumerate(zip(self.edge_functions(), edge_sets, strict=True)):
            messages = _edge_messages(function, nodes, edges, senders, receivers, per_node=k == 0)
            summed.append(torch.zeros_like(nodes).index_add_(0, receivers, messages))
            updated.append((edges + messages, senders, receivers))
        return nodes + self.node_mlp(torch.cat([nodes, *summed], dim=-1)), updated


class EdgeFunction(nn.Module):
    """The layers of f_E(E, V_r, V_s) of a further edge set (InteractionBlock applies them)."""

    def __init__(self, latent: int, hidden: int, hidden_layers: int, layer_norm: bool = True):
        super().__init__()
        _add_edge_function(self, latent, hidden, hidden_layers, layer_norm)


class EncodeProcessDecode(nn.Module):
    """Node and edge encoders (MLP + LayerNorm), L x K interaction blocks, node decoder (MLP)."""

    def __init__(self, node_in: int, edge_in: int, out_size: int, latent: int = 128, hidden: int = 128,
                 hidden_layers: int = 2, message_passing_steps: int = 10, processor_repeats: int = 1,
                 collision_edge_in: int = 0):
        super().__init__()
        self.processor_repeats = processor_repeats
        self.node_encoder = MLP(node_in, hidden, hidden_layers, latent, layer_norm=True)
        self.edge_encoder = MLP(edge_in, hidden, hidden_layers, latent, layer_norm=True)
        collisions = collision_edge_in > 0
        if collisions:
            self.collision_encoder = MLP(collision_edge_in, hidden, hidden_layers, latent, layer_norm=True)
        self.blocks = nn.ModuleList(InteractionBlock(latent, hidden, hidden_layers, collisions=collisions)
                                    for _ in range(message_passing_steps))
        self.decoder = MLP(latent, hidden, hidden_layers, out_size, layer_norm=False)

    @property
    def collisions(self) -> bool:
        return hasattr(self, "collision_encoder")

    def edge_encoders(self) -> list[nn.Module]:
        """One encoder per edge set: mesh, then collision."""
        return [self.edge_encoder, self.collision_encoder] if self.collisions else [self.edge_encoder]

    def forward(self, nodes: torch.Tensor, edges: torch.Tensor, senders: torch.Tensor,
                receivers: torch.Tensor, collision_edges: torch.Tensor | None = None,
                collision_senders: torch.Tensor | None = None, collision_receivers: torch.Tensor | None = None) -> torch.Tensor:
        """nodes (N, node_in), edges (E, edge_in), senders/receivers (E,) int64 -> (N, out_size).

        A network with collisions also takes collision_edges (C, collision_edge_in) and their
        senders/receivers (C,); C may be 0.
        """
        raw = [(edges, senders, receivers)]
        if self.collisions:
            raw.append((collision_edges, collision_senders, collision_receivers))
        v = self.node_encoder(nodes)
        sets = [(encoder(e), s, r) for encoder, (e, s, r) in zip(self.edge_encoders(), raw, strict=True)]
        for _ in range(self.processor_repeats):
            for block in self.blocks:
                v, sets = block(v, sets)
        return self.decoder(v)

    def forward_flops(self, num_nodes: int, num_edges: int, num_collision_edges: int = 0) -> int:
        """Multiply-add FLOPs (2 per MAC) of all Linear layers in one forward pass."""
        def linear_flops(module: nn.Module, rows: int) -> int:
            return sum(2 * rows * m.in_features * m.out_features
                       for m in module.modules() if isinstance(m, nn.Linear))

        counts = [num_edges, num_collision_edges][:len(self.edge_encoders())]
        block_flops = sum(
            linear_flops(b.node_mlp, num_nodes)
            + sum(linear_flops(f.edge_in, n) + linear_flops(f.edge_rest, n) + linear_flops(f.receiver_in, rows)
                  + linear_flops(f.sender_in, rows)
                  for f, n, rows in zip(b.edge_functions(), counts, (num_nodes, num_collision_edges)))
            for b in self.blocks)
        encoders = linear_flops(self.node_encoder, num_nodes) + sum(
            linear_flops(enc, n) for enc, n in zip(self.edge_encoders(), counts))
        return encoders + self.processor_repeats * block_flops + linear_flops(self.decoder, num_nodes)


# Node and edge features of a mesh graph, and the running normalisers that scale them.
#
# Features are computed from float64 positions and cast to float32 only after differencing, so
# that a scene far from the origin loses no precision (translation equivariance holds to float32
# round-off of the differences, not of the absolute coordinates).
#
# Feature groups (each normalised separately, each switchable in [features]):
#   node  velocity       (N, 6)  x_t - x_{t-1}, x_{t-1} - x_{t-2}
#         floor          (N, 1)  clip(z_t - floor_z, 0, floor_clip) (from -floor_clip with
#                                floor_signed); only if the data has a floor
#         material       (N, 2)  friction, restitution; only if the data's materials vary
#         rest_position  (N, 3)  scaled rest vertex in the body frame
#         rest_norm      (N, 1)  |rest vertex| instead, with features.body_frame_free
#         position       (N, 3)  x_t; absolute encoding only
#   edge  relative       (E, 3)  d = x_r - x_s (receiver minus sender), and |d| (E, 1)
#         rest_relative  (E, 3)  d^U = rest_r - rest_s, and |d^U| (E, 1); only |d^U| with
#                                features.body_frame_free (no body-frame vector anywhere)
#   With the absolute encoding edges get one constant zero input (E, 1), unnormalised.
#   collision  collision_relative (C, 3)  d = x_r - x_s across two objects, and |d| (C, 1);
#         only when the dataset has multi-object scenes (ModelSpec.collision_edges); no rest-shape
#         features (meaningless across objects); the same with either encoding. With
#         features.collision_velocity also collision_velocity (C, 3): v_r - v_s over the last frame.


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
        stats = torch.cat([x.sum(0), (x * x).sum(0), x.new_full((1,), x.shape[0])])
        if dist.is_available() and dist.is_initialized():
            # one vector summed over the processes: each holds the whole global batch's statistics
            from gns.processes import sum_over_processes
            stats = sum_over_processes(stats)
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

    def _stats(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """mean and std in `dtype`, made again only when the statistics changed (other buffers, or
        written in place: their version counters): a rollout step reads a dozen normalisers, and
        making them each time cost ~0.5 ms of a MOVi-A step (of ~25)."""
        state = (self.count, self.sum, self.sum_squared)
        versions = tuple(t._version for t in state)
        cache = self.__dict__.setdefault("_stats_cache", {})
        # made under inference mode they could not enter a graph autograd records: kept apart
        key = (dtype, torch.is_inference_mode_enabled())
        kept = cache.get(key)
        if kept is None or kept[1] != versions or any(a is not b for a, b in zip(kept[0], state)):
            kept = cache[key] = (state, versions, self.mean.to(dtype), self.std.to(dtype))
        return kept[2], kept[3]

    def forward(self, x: torch.Tensor, accumulate: bool = False) -> torch.Tensor:
        if accumulate:
            self.accumulate(x)
        mean, std = self._stats(x.dtype)
        return (x - mean) / std

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        mean, std = self._stats(y.dtype)
        return y * std + mean


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
    # The absolute encoding gives nodes x and x^U (paper, GNS [abs]) whatever rest_position says;
    # body_frame_free gives |x^U| for x^U and |d^U| alone for d^U, 1 wide each
    free = bool(getattr(f, "body_frame_free", False))
    if f.rest_position or absolute:
        node.append(("rest_norm", 1) if free else ("rest_position", 3))
    edge = []
    if absolute:
        node.append(("position", 3))
    else:
        edge += [("relative", 3), ("relative_norm", 1)]
        if f.rest_edges:
            edge += [("rest_relative_norm", 1)] if free else [("rest_relative", 3), ("rest_relative_norm", 1)]
    if not node:
        raise ConfigError("no node features are on: switch on features.velocity or features.rest_position")
    collision = ()
    if collisions:
        collision = ((("collision_relative", 3), ("collision_relative_norm", 1))
                     + ((("collision_anchor", 3),) if f.collision_mode == "face" else ())
                     + ((("collision_velocity", 3),) if getattr(f, "collision_velocity", False) else ()))
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
        elif name == "rest_norm":
            out[name] = graph.rest.norm(dim=-1, keepdim=True)
        elif name == "position":
            out[name] = x_t
    return {k: v.to(torch.float32) for k, v in out.items()}


def raw_edge_features(layout: FeatureLayout, history: torch.Tensor, graph: GraphBatch) -> dict[str, torch.Tensor]:
    """history (N, 3, 3) float64 -> {group: (E, width) float32} for the mesh edges."""
    s, r = graph.mesh_edges.senders, graph.mesh_edges.receivers
    out = {}
    names = {name for name, _ in layout.edge_groups}
    # gathers by index_select: half the cost of indexing x[r] (every rollout step builds these)
    if "relative" in names:
        x_t = history[:, -1]
        d = x_t.index_select(0, r) - x_t.index_select(0, s)
        out["relative"], out["relative_norm"] = d, d.norm(dim=-1, keepdim=True)
    if "rest_relative_norm" in names:
        d = graph.rest.index_select(0, r) - graph.rest.index_select(0, s)
        out["rest_relative_norm"] = d.norm(dim=-1, keepdim=True)
        if "rest_relative" in names:
            out["rest_relative"] = d
    return {k: v.to(torch.float32) for k, v in out.items()}


# the collision edge groups that are vectors in the world: turned with the receiving object's heading
COLLISION_VECTORS = frozenset({"collision_relative", "collision_anchor", "collision_velocity"})


def raw_collision_features(history: torch.Tensor, edges, velocity: bool = False) -> dict[str, torch.Tensor]:
    """history (N, 3, 3) float64, collision edges s -> r (a gns.graph.EdgeSet) -> {group: (C, width)
    float32}: d = x_r - x_s and |d|, or for surface edges (gns.contacts) the vertex minus its closest
    surface point and the signed distance; face edges (gns.face_contacts) add the receiver minus its
    contact point; `velocity` adds v_r - v_s (v = x_t - x_{t-1})."""
    if edges.vectors is not None:
        out = {"collision_relative": edges.vectors[:, :3], "collision_relative_norm": edges.signed}
        if edges.vectors.shape[1] == 6:   # face edges: the receiver from its contact point too
            out["collision_anchor"] = edges.vectors[:, 3:]
    else:
        d = history[:, -1].index_select(0, edges.receivers) - history[:, -1].index_select(0, edges.senders)
        out = {"collision_relative": d, "collision_relative_norm": d.norm(dim=-1, keepdim=True)}
    if velocity:
        v = history[:, -1] - history[:, -2]
        out["collision_velocity"] = v.index_select(0, edges.receivers) - v.index_select(0, edges.senders)
    return {k: v.to(torch.float32) for k, v in out.items()}
