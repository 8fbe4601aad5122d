"""The learned simulator: features -> network -> acceleration -> next positions, and back.

Owns everything around the network: feature building and normalisation, the loss, and the
rollout (which objects the network moves, which fly free or sleep, which nodes it sees). The
rigid-body steps it calls (the integrator x_{t+1} = x_t + (x_t - x_{t-1}) + a and its exact
inverse, shape matching) are gns.rigid; the floor's symmetries and canonical frames
gns.symmetry. Positions are float64 throughout; the network runs in float32 on normalised
features.
"""
from __future__ import annotations

import types
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import torch
from torch import nn

from gns.features import (HISTORY, FeatureLayout, Normalizer, make_layout, raw_collision_features,
                          raw_edge_features, raw_node_features)
from gns.config import ConfigError
from gns.contacts import surface_edges
from gns.graph import (EdgeSet, GraphBatch, MeshLibrary, candidate_pairs, collision_edges, graph_settings,
                       lowest_nodes, mapped_symmetries, per_graph, select_graphs, select_nodes, stack_graphs,
                       with_surface_edges, with_symmetries)
from gns.network import EncodeProcessDecode
from gns.precision import resolve_autocast
from gns.rigid import acceleration_of, integrate, posed, shape_match_packed
from gns.spec import ModelSpec
from gns.symmetry import FLOOR_SYMMETRIES, SYMMETRY_GROUPS, symmetry_group, turn_about_z


@dataclass(frozen=True)
class Sleep:
    """Deactivation of resting objects in rollouts, as physics engines do it (Bullet's sleeping).

    A learned model's acceleration at rest is never exactly zero (the small cpu model predicts
    a few % of gravity for an object lying still), and integration turns any such bias into
    drift (docs/stability.md). An object sleeps, i.e. keeps its pose, while it lies on the
    floor (lowest vertex within `contact` x its diameter of it) and every vertex moved less than
    `fraction` x |g| dt^2 in both input steps: a tenth of what gravity alone moves a body in
    one frame, which a body in flight cannot do twice in a row (its steps differ by |g| dt^2).
    As in Bullet only a contact wakes it: a collision edge from an object that is awake.
    Objects resting on other objects do not sleep (not handled). Off by default: a rollout
    option, not part of the model.
    """

    fraction: float = 0.1
    contact: float = 0.01

    def asleep(self, frames: list[torch.Tensor], graph: GraphBatch, step: float, floor_z: float | None,
               contacts: EdgeSet | None) -> torch.Tensor:
        """Node mask (N,) of the objects that sleep this step; `step` = |g| dt^2 (units per frame)."""
        return self.asleep_graphs(frames, graph, step, floor_z, contacts)[graph.node_graph]

    def asleep_graphs(self, frames: list[torch.Tensor], graph: GraphBatch, step: float, floor_z: float | None,
                      contacts: EdgeSet | None) -> torch.Tensor:
        """`asleep` per object: (G,) bool."""
        if floor_z is None:
            return torch.zeros(graph.num_graphs, dtype=torch.bool, device=graph.rest.device)
        x = frames[-1]
        moved = torch.maximum((x - frames[-2]).norm(dim=-1), (frames[-2] - frames[-3]).norm(dim=-1))
        size = 2 * per_graph(graph.rest.norm(dim=-1), graph, "amax")  # diameter of the sphere about the centre
        on_floor = per_graph(x[:, 2], graph, "amin") - floor_z < self.contact * size
        slow = (per_graph(moved, graph, "amax") < self.fraction * step) & on_floor
        if contacts is not None and len(contacts.senders):
            awake_sender = ~slow[graph.node_graph[contacts.senders]]
            woken = torch.zeros(graph.num_graphs, dtype=torch.bool, device=slow.device)
            woken[graph.node_graph[contacts.receivers[awake_sender]]] = True
            slow = slow & ~woken
        return slow


# Below this share of nodes left out of a step (free or asleep), the network runs on the whole
# batch and their rows are replaced: cutting the graph cost more than it saved at 7.5% left
# out (multi-object MOVi-style scenes, benchmarks/bench_learned_vs_physics.py).
SUBGRAPH_MIN_SHARE = 0.2

IMAGE_NODES = 32768  # most nodes in one network call of symmetrized images (predict_acceleration)


class _OwnCode(nn.Module):
    """The network as torch.compile should see it (set_speed). torch.compile caches compiled code
    per code object, up to dynamo's recompile_limit (8) entries, then runs eager, silently; the
    network's own forward is one code object for every model of the class. So two compiles of one
    network (frozen for rollouts, unfrozen for training) would share graphs, whichever came first,
    and the ninth compiled model of a process (an ensemble, a benchmark, a script scoring many
    runs; found scoring 12 in one) ran eager. Each instance's forward is a code object of its own."""

    def __init__(self, network: nn.Module):
        super().__init__()
        self.network = network
        f = type(self)._forward
        self.forward = types.MethodType(types.FunctionType(f.__code__.replace(), f.__globals__, "forward"), self)

    def _forward(self, *args: torch.Tensor) -> torch.Tensor:
        return self.network(*args)


def _pose_where(mask: torch.Tensor, a: tuple, b: tuple) -> tuple[torch.Tensor, torch.Tensor]:
    """Per object, pose a (R (G, 3, 3), t (G, 3)) where mask (G,) is True, else pose b."""
    return torch.where(mask[:, None, None], a[0], b[0]), torch.where(mask[:, None], a[1], b[1])


def _listed(t: torch.Tensor | None) -> list | None:
    """A small tensor as a list, for comparisons and messages."""
    return None if t is None else [round(float(v), 12) for v in t.reshape(-1)]


def _surface_free(settings: dict, other: "LearnedSimulator") -> dict:
    """Graph settings as an ensemble compares them: surface_edges left out where both models have
    centre nodes (the spokes are then rebuilt exactly)."""
    if settings["centre_node"] and other._graph_settings["centre_node"]:
        return {k: v for k, v in settings.items() if k != "surface_edges"}
    return settings


class LearnedSimulator(nn.Module):
    """GNS for rigid meshes. `spec` is what it is trained on (gns.spec.ModelSpec; gns.data.feature_spec)."""

    symmetrize: bool | str = False  # average predictions over SYMMETRY_GROUPS (True: "d2"; rollouts; not saved)
    body_frames: bool = False  # and over each object's equivalent body frames (graph.symmetries)
    free_clearance: float | None = None  # free flight's height above the floor (None: the floor clip; not saved)
    autocast: torch.dtype | None = None  # the network (only) runs in this dtype under autocast (train.autocast)
    autocast_used: str = "none"  # what set_speed took: "none" or "bf16" ("auto" resolved)

    def __init__(self, model_cfg, features_cfg, spec: ModelSpec | Mapping):
        super().__init__()
        if not isinstance(spec, ModelSpec):  # a dict of a few keys, as benchmarks/ build untrained simulators
            spec = ModelSpec.from_dict(spec, partial=True)
        # what Sleep's threshold is made of: |g| dt^2, in scene units per frame
        self.gravity_step = spec.gravity_step
        # the same as a vector: the centre's second difference in free flight (units per frame^2)
        self.gravity_per_frame = spec.gravity_per_frame
        self.collision_mode = features_cfg.collision_mode  # "vertex" or "surface", checked by gns.config
        # the graphs this model reads: self.mesh_library(meshes)
        self._graph_settings = graph_settings(features_cfg)
        self.canonical_heading = bool(getattr(features_cfg, "canonical_heading", False))
        self.lowest_vertices = int(getattr(features_cfg, "lowest_vertices", 0))
        self.highest_vertices = int(getattr(features_cfg, "highest_vertices", 0))
        self.layout: FeatureLayout = make_layout(features_cfg, spec.floor_z, spec.materials_vary,
                                                 collisions=spec.collision_edges)
        if self.lowest_vertices and self.layout.floor_z is None:
            raise ConfigError("features.lowest_vertices needs a floor (\"lowest\" means nearest the floor)")
        if self.lowest_vertices and self.layout.collisions and self.collision_mode != "vertex":
            # a vertex-to-surface edge needs the other object's faces, which a cut graph loses
            raise ConfigError("features.lowest_vertices with collision edges needs features.collision_mode=vertex")
        steps = features_cfg.normalizer_steps
        self.node_normalizers = nn.ModuleDict({n: Normalizer(w, steps) for n, w in self.layout.node_groups})
        self.edge_normalizers = nn.ModuleDict({n: Normalizer(w, steps) for n, w in self.layout.edge_groups})
        if self.layout.collisions:  # absent (not even empty) without collisions: old checkpoints load unchanged
            self.collision_normalizers = nn.ModuleDict(
                {n: Normalizer(w, steps) for n, w in self.layout.collision_groups})
        self.target_normalizer = Normalizer(3, steps)
        self.network = EncodeProcessDecode(
            self.layout.node_size, self.layout.edge_size, 3, latent=model_cfg.latent_size,
            hidden=model_cfg.hidden_size, hidden_layers=model_cfg.hidden_layers,
            message_passing_steps=model_cfg.message_passing_steps,
            processor_repeats=model_cfg.processor_repeats, collision_edge_in=self.layout.collision_size)

    @property
    def centre_node(self) -> bool:
        return self._graph_settings["centre_node"]

    def mesh_library(self, meshes: dict) -> MeshLibrary:
        """The graphs of `meshes` as this model's network reads them, as trained (graph_settings)."""
        return MeshLibrary(meshes, **self._graph_settings)

    def distribute(self, wrapper: nn.Module | None) -> None:
        """Train the network through `wrapper` (a DistributedDataParallel of self.network, which
        averages gradients over processes). Kept out of the module tree, so state_dict keys and
        checkpoints stay those of one process; eval mode calls the network directly."""
        self.__dict__["_parallel"] = wrapper

    def set_speed(self, autocast: str = "none", compile: bool = False, freeze: bool = False) -> None:
        """How the network runs: autocast "bf16" (the network only, under bfloat16 autocast) or
        "none"; `compile` through torch.compile (dynamic shapes: every batch has its own node and
        edge counts), compiled once and reused when switched on again. The compiled module is
        kept out of the module tree like `distribute`, so state_dict keys and checkpoints are
        unchanged. The first calls compile (tens of seconds on a CPU). autocast "auto": bf16 if it
        measures faster here (gns.precision); `self.autocast_used` says which was taken.

        `freeze` (with `compile`, for rollouts of a trained model only): inductor's freezing, which
        takes the weights as constants at the first call and lays them out for the CPU's matrix
        kernels once (6-7% off a rollout here, docs/speed.md). Weights changed after
        that call are not seen, so a training never freezes; in training mode the unfrozen
        compile (or the plain network) runs."""
        if autocast != "none":   # auto decides here; bf16 on a CPU that emulates it warns
            device = next(self.network.parameters()).device
            autocast = resolve_autocast(autocast, self.network.decoder[0].in_features, device)
        self.autocast_used = autocast
        self.autocast = torch.bfloat16 if autocast == "bf16" else None
        if compile and "_compiled_cache" not in self.__dict__:
            self.__dict__["_compiled_cache"] = torch.compile(_OwnCode(self.network), dynamic=True)
        if compile and freeze and "_frozen_cache" not in self.__dict__:
            self.__dict__["_frozen_cache"] = torch.compile(_OwnCode(self.network), dynamic=True)
        self.__dict__["_compiled"] = self.__dict__["_compiled_cache"] if compile else None
        self.__dict__["_frozen"] = self.__dict__["_frozen_cache"] if compile and freeze else None

    def run_network(self, *args: torch.Tensor) -> torch.Tensor:
        wrapper = self.__dict__.get("_parallel")
        compiled = self.__dict__.get("_compiled")
        frozen = None if self.training or torch.is_grad_enabled() else self.__dict__.get("_frozen")
        if frozen is not None:
            # freezing is read when a call compiles (the first, or a shape that recompiles); torch.compile's
            # options do not carry it there
            with torch._inductor.config.patch(freezing=True):
                return self._call(frozen, args)
        network = wrapper if wrapper is not None and self.training else \
            (self.network if compiled is None else compiled)
        return self._call(network, args)

    def _call(self, network, args: tuple) -> torch.Tensor:
        if self.autocast is None:
            return network(*args)
        # features, normalisers, the integrator and shape matching stay outside, in float32/float64
        with torch.autocast(args[0].device.type, dtype=self.autocast):
            out = network(*args)
        return out.to(torch.float32)

    def collision_edges(self, x: torch.Tensor, graph: GraphBatch) -> EdgeSet:
        """The graph's collision edges if given, else built from positions x (N, 3)."""
        if graph.collision_edges is not None:
            return graph.collision_edges
        if self.collision_mode == "surface":
            return surface_edges(x, graph, self.layout.collision_radius)
        return collision_edges(x, graph, self.layout.collision_radius)

    def _inputs(self, history: torch.Tensor, graph: GraphBatch) -> tuple[torch.Tensor, list[tuple]]:
        """history (N, 3, 3) float64 -> normalised node inputs (N, Fn) float32 and one
        (features, senders, receivers) per edge set: the mesh edges, then (with collisions) the
        collision edges, built from x_t here unless the graph brings them, so that a rollout
        rebuilds them from its own predictions at every step.

        Normalisers accumulate statistics while the module is in training mode.
        """
        acc = self.training
        raw_nodes = raw_node_features(self.layout, history, graph)
        nodes = torch.cat([self.node_normalizers[n](raw_nodes[n], acc) for n, _ in self.layout.node_groups], -1)
        if self.layout.absolute:
            edges = torch.zeros(graph.mesh_edges.senders.shape[0], 1, device=history.device)
        else:
            raw_edges = raw_edge_features(self.layout, history, graph)
            edges = torch.cat([self.edge_normalizers[n](raw_edges[n], acc) for n, _ in self.layout.edge_groups], -1)
        edge_sets = [(edges, graph.mesh_edges.senders, graph.mesh_edges.receivers)]
        if self.layout.collisions:
            c = self.collision_edges(history[:, -1], graph)
            raw = raw_collision_features(history, c)
            features = torch.cat([self.collision_normalizers[n](raw[n], acc) for n, _ in self.layout.collision_groups], -1)
            edge_sets.append((features, c.senders, c.receivers))
        return nodes, edge_sets

    def forward(self, history: torch.Tensor, graph: GraphBatch) -> torch.Tensor:
        """history (N, 3, 3) float64 positions at t-2, t-1, t -> normalised acceleration (N, 3) float32."""
        if self.canonical_heading:
            return self._forward_canonical(history, graph)
        nodes, edge_sets = self._inputs(history, graph)
        return self.run_network(nodes, *(t for edge_set in edge_sets for t in edge_set))

    def _forward_canonical(self, history: torch.Tensor, graph: GraphBatch) -> torch.Tensor:
        """forward with each scene turned to its canonical heading (features.canonical_heading):
        about z, so that the mean horizontal velocity of its nodes over the last frame points
        along +x; the acceleration is turned back in scene units (the target normaliser's x and
        y statistics need not match). A scene at rest keeps its heading (atan2(0, 0) = 0)."""
        scene = graph.node_scene
        count = int(scene.max()) + 1 if scene.numel() else 0
        step = (history[:, -1, :2] - history[:, -2, :2])
        velocity = torch.zeros(count, 2, dtype=history.dtype, device=history.device).index_add_(0, scene, step)
        angle = -torch.atan2(velocity[:, 1], velocity[:, 0])
        cos, sin = torch.cos(angle).index_select(0, scene), torch.sin(angle).index_select(0, scene)
        turned = turn_about_z(history, cos, sin)
        nodes, edge_sets = self._inputs(turned, graph)
        out = self.run_network(nodes, *(t for edge_set in edge_sets for t in edge_set))
        acc = self.target_normalizer.inverse(out.to(history.dtype))
        acc = turn_about_z(acc, cos, -sin)   # the turn undone
        return self.target_normalizer(acc).to(torch.float32)

    def set_ensemble(self, members: Sequence["LearnedSimulator"]) -> None:
        """Average every step's predicted acceleration with these models' (an ensemble: runs
        trained apart, e.g. other seeds or other recipes; each carries its own normalisers and
        speed settings and computes its own node and edge features from the shared graphs).
        They must read the same graphs: the same network mesh, floor, collision edges and time
        step; ValueError names the first difference. Node and edge features may
        differ (e.g. the floor seen from farther): free flight then waits until every member's
        floor feature is clear (free_flight_clip). With centre nodes on both, a member may differ in
        features.surface_edges alone: it reads each step's graph with its own mesh edges, rebuilt
        from the faces (gns.graph.with_surface_edges)."""
        for k, m in enumerate(members, 1):
            for what, mine, theirs in (("network mesh (features.centre_node, surface_edges)",
                                        _surface_free(self._graph_settings, m), _surface_free(m._graph_settings, self)),
                                       ("floor height", self.layout.floor_z, m.layout.floor_z),
                                       ("collision edges (features and radius)",
                                        (self.layout.collision_groups, self.layout.collision_radius),
                                        (m.layout.collision_groups, m.layout.collision_radius)),
                                       ("time step and gravity", _listed(self.gravity_per_frame),
                                        _listed(m.gravity_per_frame)),
                                       ("nodes seen (features.lowest_vertices, highest_vertices)",
                                        (self.lowest_vertices, self.highest_vertices),
                                        (m.lowest_vertices, m.highest_vertices))):
                if mine != theirs:
                    raise ValueError(f"ensemble member {k} differs from the model in its {what}: "
                                     f"{theirs} there, {mine} in the model")
        self.__dict__["_members"] = list(members)

    @property
    def members(self) -> list:
        """The ensemble members set by set_ensemble (empty without)."""
        return list(self.__dict__.get("_members") or ())

    @property
    def free_flight_clip(self) -> float:
        """How far above the floor an object must stay to be in free flight: the largest floor
        clip of this model and its ensemble members (beyond it no member's network sees the floor,
        so the exact update is what the network would approximate), or `free_clearance` if set.
        A clearance below the clip also takes the band where the network sees the floor but no
        vertex can reach it within the step (now or after the ballistic step): fewer object-steps
        in the network, at an accuracy measured in docs/speed.md."""
        if self.free_clearance is not None:
            return float(self.free_clearance)
        return max([self.layout.floor_clip] + [m.layout.floor_clip for m in self.members])

    def predict_acceleration(self, history: torch.Tensor, graph: GraphBatch) -> torch.Tensor:
        """(N, 3, 3) float64 -> acceleration (N, 3) float64, scene units per frame^2: this model's
        prediction, averaged with its ensemble members' (set_ensemble) if any, each symmetrized
        as this model is asked to be."""
        acc = self._predict_one(history, graph, self.symmetrize, self.body_frames)
        members = self.__dict__.get("_members")
        if not members:  # the rollout's hot path: no extra tensor work without an ensemble
            return acc
        for m in members:
            own = m._graph_settings["surface_edges"]
            seen = graph if own == self._graph_settings["surface_edges"] else with_surface_edges(graph, own)
            acc = acc + m._predict_one(history, seen, self.symmetrize, self.body_frames)
        return acc / (1 + len(members))

    def _predict_one(self, history: torch.Tensor, graph: GraphBatch, symmetrize: bool, body_frames: bool) -> torch.Tensor:
        """This model's acceleration (N, 3) float64.

        With `symmetrize` (`self.symmetrize`, a rollout option, off by default), it is averaged over
        the world's floor symmetries {identity, mirror x, mirror y, half turn about z}: each maps
        the input, the network predicts, the map is undone. The result is exactly equivariant
        to those four maps applied to the scene, body frames included (a cube tilted 45 + d is the mirror
        of one tilted 45 - d only up to its body frame: docs/diagnostic_45.md), where
        the network alone is only approximately so (trained with random z rotations).
        With `body_frames` too, each object's rest shape is also described in every one of
        its equivalent body frames (graph.symmetries, the rotations mapping its mesh onto itself,
        e.g. a cube's 24) and the predictions averaged: exactly invariant to which frame describes
        an object, at that many times the cost."""
        syms = graph.symmetries if body_frames else None
        if not symmetrize and syms is None:
            return self.target_normalizer.inverse(self(history, graph).to(torch.float64))
        group = symmetry_group(symmetrize)
        floors = SYMMETRY_GROUPS[group] if group else FLOOR_SYMMETRIES[:1]
        frames = 1 if syms is None else syms.shape[1]
        inputs, graphs, maps = [], [], []
        for k in range(frames):
            if syms is None:
                rest, weight = graph.rest, 1.0
            else:
                # the same world vertices described in the k-th equivalent body frame (r -> S r):
                # the answer may not hang on which one, so average over all of each object's group
                rest = torch.einsum("nij,nj->ni", syms[graph.node_graph, k], graph.rest)
                counts = graph.num_symmetries[graph.node_graph]
                weight = ((k < counts).to(history.dtype) / counts.to(history.dtype))[:, None]
            for m in floors:
                g = torch.tensor(m, dtype=history.dtype, device=history.device)
                # the body frame is mapped too (x = R rest + p -> (g R g^T) (g rest) + g p): the
                # network sees a proper rotation, as in training, and the average is exactly equivariant
                inputs.append(history @ g.T)
                graphs.append(replace(graph, rest=rest @ g.T, collision_edges=None,
                                      symmetries=mapped_symmetries(graph, g)))
                maps.append((g, weight))
        # images share network calls: per node, a call on 6400 nodes costs ~0.6x one on 1600;
        # calls stay under IMAGE_NODES nodes (24 body frames x 4 mirrors of a batch would not fit)
        per_call = max(1, IMAGE_NODES // max(graph.num_nodes, 1))
        total = torch.zeros_like(history[:, -1])
        for lo in range(0, len(maps), per_call):
            hi = min(lo + per_call, len(maps))
            out = self.target_normalizer.inverse(
                self(torch.cat(inputs[lo:hi]), stack_graphs(graphs[lo:hi])).to(torch.float64))
            for a, (g, weight) in zip(out.split(graph.num_nodes), maps[lo:hi]):
                total = total + (a @ g) * weight   # g^T a: the map undone
        return total / len(floors)

    def network_nodes(self, x_t: torch.Tensor, graph: GraphBatch) -> tuple[GraphBatch, torch.Tensor] | None:
        """With features.lowest_vertices = k: the graph of each object's k vertices nearest the floor
        at x_t (N, 3) (and its features.highest_vertices highest), its centre and, with collision
        edges, every vertex that has one, and those nodes' indices; None where the network sees
        every node. The cut graph carries the collision edges of the whole one: both ends of each
        are kept, so the network sees every contact between objects, however high it is."""
        if not self.lowest_vertices:
            return None
        keep = lowest_nodes(x_t[:, 2], graph, self.lowest_vertices, self.highest_vertices)
        if self.layout.collisions:
            contacts = self.collision_edges(x_t, graph)
            keep = keep.index_fill(0, contacts.senders, True)   # edges come both ways: receivers too
            graph = replace(graph, collision_edges=contacts)
        return None if bool(keep.all()) else select_nodes(graph, keep)

    def predict_next(self, x_tm2: torch.Tensor, x_tm1: torch.Tensor, x_t: torch.Tensor, graph: GraphBatch,
                     fitted: list | None = None) -> torch.Tensor:
        """Vertex positions (N, 3) float64 at t-2, t-1, t -> positions at t+1 (N, 3) float64.

        With features.lowest_vertices the network moves the nodes it sees (network_nodes) and every
        other vertex takes the pose shape matching fits to those: a rollout's shape matching of
        all of them then finds that same pose, which is appended to `fitted` (if given) as
        (R (G, 3, 3), t (G, 3)) so that a rollout need not fit it again."""
        seen = self.network_nodes(x_t, graph)
        if seen is None:
            return self._predict_next(x_tm2, x_tm1, x_t, graph)
        sub, nodes = seen
        part = self._predict_next(*(f.index_select(0, nodes) for f in (x_tm2, x_tm1, x_t)), sub)
        rot, t, _ = shape_match_packed(part, sub.rest, sub.node_graph, sub.num_graphs)
        if fitted is not None:
            fitted.append((rot, t))
        x = posed(rot, t, graph.node_graph, graph.rest)
        return x.index_put((nodes,), part)

    def _predict_next(self, x_tm2: torch.Tensor, x_tm1: torch.Tensor, x_t: torch.Tensor, graph: GraphBatch) -> torch.Tensor:
        history = torch.stack([x_tm2, x_tm1, x_t], dim=1)
        return integrate(x_tm1, x_t, self.predict_acceleration(history, graph))

    def in_free_flight(self, frames: list[torch.Tensor], ballistic: torch.Tensor, graph: GraphBatch,
                       contacts: EdgeSet | None) -> torch.Tensor:
        """(G,) objects out of reach of the floor and of every other object for the whole step:
        every vertex at least the floor feature's clip above the floor both now and after the
        ballistic step (`ballistic`, (N, 3) at t+1), so the network sees no floor; no collision
        edge now; and no other object's box, swept over the last and the next step, within the
        collision radius of its own swept box, so none can appear. The network's answer for such
        an object depends on its own motion only: its learned free flight, which the exact
        inertial update replaces. (Free only at t measured 25.9% position against 29.0% with the
        network everywhere on MOVi-A, but penetration 0.38% against 0.29%: an object one step
        from the floor had been moved into it; docs/speed.md.)"""
        x = frames[-1]
        free = torch.ones(graph.num_graphs, dtype=torch.bool, device=x.device)
        if self.layout.floor_z is not None:
            clear = self.layout.floor_z + self.free_flight_clip
            free &= (per_graph(x[:, 2], graph, "amin") >= clear) & (per_graph(ballistic[:, 2], graph, "amin") >= clear)
        if self.layout.collisions:
            if contacts is not None and len(contacts.senders):
                free[graph.node_graph[contacts.senders]] = False
            if graph.graph_scene is not None and graph.num_graphs > 1:
                # each object's box swept over x_{t-1}, x_t and the ballistic x_{t+1}: a pair whose
                # swept boxes come within the collision radius may touch during the step
                swept = torch.stack([frames[-2], x, ballistic])
                low = per_graph(swept.amin(0), graph, "amin")
                high = per_graph(swept.amax(0), graph, "amax")
                a, b = candidate_pairs(graph)
                r = self.layout.collision_radius
                near = ((low[a] - high[b] <= r) & (low[b] - high[a] <= r)).all(dim=1)
                free[a[near]] = False
                free[b[near]] = False
        return free

    def inertial_pose(self, pose_tm1: tuple[torch.Tensor, torch.Tensor],
                      pose_t: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Free flight, exactly: the centre of mass keeps its velocity plus gravity's g dt^2 and the
        body turns by the same rotation as in the last frame (constant angular velocity; exact for
        the isotropic inertia of cubes and spheres, which is also what shape matching assumes of a
        mesh). Poses (R (G, 3, 3), t (G, 3)) at t-1 and t -> the pose at t+1."""
        (r0, t0), (r1, t1) = pose_tm1, pose_t
        return r1 @ r0.transpose(1, 2) @ r1, 2 * t1 - t0 + self.gravity_per_frame.to(t1)

    def advance(self, frames: list[torch.Tensor], graph: GraphBatch, sleep: Sleep | None = None, free_flight: bool = False,
                pose: list | None = None, counts: dict | None = None, fitted: list | None = None) -> torch.Tensor:
        """One rollout step: positions (N, 3) at t+1 from frames [..., x_{t-2}, x_{t-1}, x_t], before
        shape matching. Sleeping objects keep x_t, free ones (with `free_flight`; `pose` holds the
        (R, t) of the last two frames) take the inertial update, the rest the network's answer.
        `counts` (if given) adds this step's object-steps: in the network, free, asleep. With
        `fitted` (a list) and free flight, a model with features.lowest_vertices appends every
        object's pose at t+1, (R (G, 3, 3), t (G, 3)), which shape matching the returned
        positions would find (the pose fitted to the network's nodes, the ballistic one, the one
        kept), if rigid frames were given."""
        counts = {} if counts is None else counts
        for key in ("object_steps", "network", "free_flight", "asleep"):
            counts.setdefault(key, 0)
        if free_flight and pose is None:
            pose = [shape_match_packed(f, graph.rest, graph.node_graph, graph.num_graphs)[:2] for f in frames[-2:]]
        step_graph, contacts = graph, None
        if self.layout.collisions and (sleep is not None or free_flight):
            # built once from x_t: the network, the wake-up and the free-flight tests share them
            contacts = self.collision_edges(frames[-1], graph)
            step_graph = replace(graph, collision_edges=contacts)
        skip = torch.zeros(graph.num_graphs, dtype=torch.bool, device=frames[-1].device)
        if sleep is not None:
            sleeping = sleep.asleep_graphs(frames, graph, self.gravity_step, self.layout.floor_z, contacts)
            counts["asleep"] += int(sleeping.sum())
            skip |= sleeping
        if free_flight:
            flight = self.inertial_pose(*pose)
            ballistic = posed(*flight, graph.node_graph, graph.rest)
            free = self.in_free_flight(frames, ballistic, graph, contacts) & ~skip
            counts["free_flight"] += int(free.sum())
            skip |= free
        skip_node = skip[graph.node_graph]
        # where a skipped object goes: free ones fly, sleeping ones keep their pose
        held = torch.where(free[graph.node_graph, None], ballistic, frames[-1]) if free_flight else frames[-1]
        fit = [] if fitted is not None and free_flight else None
        if fit is not None:   # the poses of `held`: the ballistic one, or the one at t
            held_pose = _pose_where(free, flight, pose[1])
        if int(skip_node.sum()) < SUBGRAPH_MIN_SHARE * graph.num_nodes:
            # few to leave out: one call on everything is cheaper than cutting the graph, and
            # the others' answers are the same (a skipped object shares no edge with them)
            x = self.predict_next(*frames[-HISTORY:], step_graph, fit)
            counts["network"] += graph.num_graphs
            if skip.any():
                x = torch.where(skip_node[:, None], held, x)
            if fit:
                fitted.append(_pose_where(skip, held_pose, fit[0]))
        else:
            x = held
            needed = ~skip
            if contacts is not None and len(contacts.senders):
                # a skipped object whose vertices an active one feels (a sleeper touching a
                # woken one) enters the call too, so the active one's answer is unchanged
                feeds = needed[graph.node_graph[contacts.receivers]]
                needed = needed.clone()
                needed[graph.node_graph[contacts.senders[feeds]]] = True
            if needed.any():
                sub, nodes = select_graphs(step_graph, needed)
                pred = self.predict_next(*(f[nodes] for f in frames[-HISTORY:]), sub, fit)
                use = ~skip[graph.node_graph[nodes]]
                x = x.index_put((nodes[use],), pred[use])  # out of place: gradients pass
                counts["network"] += int(needed.sum())
                if fit:
                    graphs = needed.nonzero()[:, 0]
                    kept = ~skip[graphs]
                    fitted.append(tuple(h.index_put((graphs[kept],), a[kept]) for a, h in zip(fit[0], held_pose)))
            elif fit is not None:
                fitted.append(held_pose)
        counts["object_steps"] += graph.num_graphs
        return x

    @torch.no_grad()
    def rollout(self, history: torch.Tensor, graph: GraphBatch, steps: int, shape_matching: bool = True,
                sleep: Sleep | None = None, free_flight: bool = False, poses: bool = False):
        """Run on its own predictions from history (N, 3, 3) float64 -> positions (steps, N, 3).

        With shape_matching, each prediction is replaced by the rigid projection of the rest mesh
        before it enters the history (paper, rollouts only). With `sleep`, objects at rest keep
        their pose until the model predicts a real acceleration (see Sleep). With `free_flight`,
        objects out of reach of the floor and of every other object (`in_free_flight`) follow the
        exact inertial update (`inertial_pose`) instead of the network, and only the others enter
        the network call; sleeping objects do not enter it either. `self.rollout_counts` then says
        how many object-steps did. With `poses`, also returns every predicted frame's pose from
        shape matching, rotations (steps, G, 3, 3) and translations (steps, G, 3).
        """
        if sleep is not None and not self.gravity_step:
            raise ValueError("sleeping needs the model's gravity and frame rate (spec)")
        if free_flight and self.gravity_per_frame is None:
            raise ValueError("free flight needs the model's gravity and frame rate (spec)")
        if self.body_frames and graph.symmetries is None:
            graph = with_symmetries(graph)
        frames = list(history.unbind(1))
        pose = [shape_match_packed(f, graph.rest, graph.node_graph, graph.num_graphs)[:2] for f in frames[-2:]] \
            if free_flight else None
        out, rots, trans = [], [], []
        counts = {"object_steps": 0, "network": 0, "free_flight": 0, "asleep": 0}
        for _ in range(steps):
            # with shape matching every frame is rigid, and a model that fits poses to a few
            # nodes (features.lowest_vertices) hands them over: no second fit of all nodes
            fitted = [] if shape_matching and free_flight and self.lowest_vertices else None
            x = self.advance(frames, graph, sleep, free_flight, pose, counts, fitted)
            if fitted:
                rot, t = fitted[0]
                matched = posed(rot, t, graph.node_graph, graph.rest)
            elif shape_matching or poses or free_flight:
                rot, t, matched = shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)
            if shape_matching or poses or free_flight:
                if shape_matching:
                    x = matched
                if poses:
                    rots.append(rot)
                    trans.append(t)
                if free_flight:
                    pose = [pose[1], (rot, t)]
            frames.append(x)
            out.append(x)
        self.rollout_counts = counts
        if poses:
            return torch.stack(out), torch.stack(rots), torch.stack(trans)
        return torch.stack(out)

    def loss(self, history: torch.Tensor, target: torch.Tensor, graph: GraphBatch, rigid: float = 0.0) -> torch.Tensor:
        """Per-node MSE of the normalised acceleration: mean over nodes of the sum over x, y, z.

        history (N, 3, 3) float64 (possibly noisy) inputs; target (N, 3) float64 positions at t+1
        (already corrected for the input noise). The target normaliser accumulates in training.
        rigid > 0 adds rigid x the same loss of the shape-matched prediction against the
        shape-matched target (train.rigid_loss): what a rollout keeps of a step. Shape matching
        runs through the differentiable polar factor (`gns.rigid._rotation_differentiable`).
        """
        seen = self.network_nodes(history[:, -1], graph)
        if seen is not None:   # the loss of the nodes the network sees (predict_next)
            graph, nodes = seen
            history, target = history[nodes], target[nodes]
        if rigid == 0:
            accel = acceleration_of(history[:, -2], history[:, -1], target).to(torch.float32)
        else:
            prior = history[:, -1] + (history[:, -1] - history[:, -2])
            accel = (target - prior).to(torch.float32)
        target_norm = self.target_normalizer(accel, accumulate=self.training)
        output = self(history, graph)
        per = ((output - target_norm) ** 2).sum(-1)
        if rigid > 0:
            # the prediction and the truth as rollouts keep them, differenced in normalised units
            # (the normaliser's spread, not its mean: a difference of positions)
            n, scale = graph.node_graph, self.target_normalizer.std.to(torch.float64)
            moved = prior + self.target_normalizer.inverse(output.to(torch.float64))
            kept = shape_match_packed(moved, graph.rest, n, graph.num_graphs)[2]
            with torch.no_grad():
                truth = shape_match_packed(target, graph.rest, n, graph.num_graphs)[2]
            per = per + rigid * (((kept - truth) / scale).to(torch.float32) ** 2).sum(-1)
        return per.mean()
