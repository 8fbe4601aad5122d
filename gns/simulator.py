"""The learned simulator: features -> network -> acceleration -> next positions, and back.

Owns everything around the network: feature building and normalisation, how the network runs
(autocast, compile), the ensemble, which nodes it sees, and the loss. The rollout (which objects
the network moves, which fly free or sleep) is gns.stepping, which LearnedSimulator inherits; the
rigid-body steps (the integrator x_{t+1} = x_t + (x_t - x_{t-1}) + a and its exact inverse, shape
matching) are gns.geometry; the symmetries a step may average over gns.symmetry.
Positions are float64 throughout; the network runs in float32 on normalised features.
"""
from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from dataclasses import replace

import torch
from torch import nn

from gns.config import ConfigError
from gns.contact_network import check_contact, split_acceleration
from gns.geometry import acceleration_of, fit_packed, integrate, placed_around, shape_match_packed
from gns.graph import EdgeSet, GraphBatch, MeshLibrary, graph_settings, lowest_nodes, select_graph_nodes, select_nodes
from gns.network import (COLLISION_VECTORS, EncodeProcessDecode, FeatureLayout, Normalizer, make_layout,
                         raw_collision_features, raw_edge_features, raw_node_features)
from gns.spec import ModelSpec, OptionsError, RolloutOptions
from gns.stepping import Stepping

# the options applied when a model is loaded (gns.checkpoint.load_simulator), not per rollout
LOAD_OPTIONS = ("autocast", "compile", "ensemble")


class LearnedSimulator(Stepping, nn.Module):
    """GNS for rigid meshes. `spec` is what it is trained on (gns.spec.ModelSpec; gns.data.feature_spec);
    `options` how it is rolled out (gns.spec.RolloutOptions; not saved with the model)."""

    autocast: torch.dtype | None = None  # the network (only) runs in this dtype under autocast (train.autocast)
    autocast_used: str = "none"  # what set_speed took: "none" or "bf16" ("auto" resolved)
    contact_model: "LearnedSimulator | None" = None  # set_contact_model

    def __init__(self, model_cfg, features_cfg, spec: ModelSpec | Mapping, options: RolloutOptions | None = None):
        super().__init__()
        self.__dict__["_options"] = RolloutOptions() if options is None else options
        if not isinstance(spec, ModelSpec):  # a dict of a few keys, as benchmarks/ build untrained simulators
            spec = ModelSpec.from_dict(spec, partial=True)
        # what Sleep's threshold is made of: |g| dt^2, in scene units per frame
        self.gravity_step = spec.gravity_step
        # the same as a vector: the centre's second difference in free flight (units per frame^2)
        self.gravity_per_frame = spec.gravity_per_frame
        self.collision_mode = features_cfg.collision_mode  # "vertex", "surface" or "face", checked by gns.config
        # the graphs this model reads: self.mesh_library(meshes)
        self._graph_settings = graph_settings(features_cfg)
        self.canonical_heading = bool(getattr(features_cfg, "canonical_heading", False))
        self.lowest_vertices = int(getattr(features_cfg, "lowest_vertices", 0))
        self.highest_vertices = int(getattr(features_cfg, "highest_vertices", 0))
        self.layout: FeatureLayout = make_layout(features_cfg, spec.floor_z, spec.materials_vary,
                                                 collisions=spec.collision_edges)
        if self.lowest_vertices and self.layout.floor_z is None:
            raise ConfigError("features.lowest_vertices needs a floor (\"lowest\" means nearest the floor)")
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
    def options(self) -> RolloutOptions:
        return self.__dict__["_options"]

    @options.setter
    def options(self, options: RolloutOptions) -> None:
        """Other rollout options for the same loaded model. Those of LOAD_OPTIONS took effect when
        it was loaded (the network's precision, its compiled code, the ensemble's members): a
        change of them would not, so it is refused."""
        changed = [k for k in LOAD_OPTIONS if getattr(options, k) != getattr(self.options, k)]
        if changed:
            raise OptionsError(f"{', '.join(changed)} take effect when the model is loaded "
                               "(gns.checkpoint.load_simulator), not after")
        self.__dict__["_options"] = options

    @contextlib.contextmanager
    def using(self, **changes):
        """These options changed (RolloutOptions fields; None keeps one) for the rollouts within,
        restored after: one loaded model rolled out several ways (a benchmark's variants)."""
        before = self.options
        self.options = before.replace(**changes)
        try:
            yield self
        finally:
            self.options = before

    @property
    def symmetrize(self) -> str | None:
        """The group of floor symmetries each step averages over (None: none)."""
        return self.options.symmetry_group

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
        """How the network runs: autocast "bf16" (the network only, under bfloat16 autocast), "none",
        or "auto" (bf16 if it measures faster here, gns.speedups; `self.autocast_used` says which);
        `compile` through torch.compile (dynamic shapes), compiled once (tens of seconds on a CPU)
        and kept out of the module tree like `distribute`, so checkpoints are unchanged.

        `freeze` (with `compile`, for rollouts of a trained model only): inductor's freezing, which
        takes the weights as constants at the first call and lays them out for the CPU's matrix
        kernels once (6-7% off a rollout here, experiments/log.md). Weights changed after
        that call are not seen, so a training never freezes; in training mode the unfrozen
        compile (or the plain network) runs."""
        if autocast != "none":   # auto decides here; bf16 on a CPU that emulates it warns
            from gns.speedups import resolve_autocast
            device = next(self.network.parameters()).device
            autocast = resolve_autocast(autocast, self.network.decoder[0].in_features, device)
        self.autocast_used = autocast
        self.autocast = torch.bfloat16 if autocast == "bf16" else None
        if compile:
            from gns.speedups import compiled
        if compile and "_compiled_cache" not in self.__dict__:
            self.__dict__["_compiled_cache"] = compiled(self.network)
        if compile and freeze and "_frozen_cache" not in self.__dict__:
            self.__dict__["_frozen_cache"] = compiled(self.network)
        self.__dict__["_compiled"] = self.__dict__["_compiled_cache"] if compile else None
        self.__dict__["_frozen"] = self.__dict__["_frozen_cache"] if compile and freeze else None

    def compile_contacts(self, on: bool = True) -> None:
        """Face edges' triangle-pair tests, distances and closest points through compiled code
        (gns.face_contacts.face_edges' `compiled`) whatever the network runs as. Training turns it
        on for runs long enough to repay the compile: the distances are most of a face-edge
        training step, the network's own compile does not pay there (experiments/log.md)."""
        self.__dict__["_compiled_contacts"] = on

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
        # imported here: a model of single objects never builds them
        from gns.contacts import collision_edges, surface_edges
        if self.collision_mode == "surface":
            return surface_edges(x, graph, self.layout.collision_radius)
        if self.collision_mode == "face":
            from gns.face_contacts import face_edges
            compiled = self.__dict__.get("_compiled") is not None or self.__dict__.get("_compiled_contacts", False)
            return face_edges(x, graph, self.layout.collision_radius, compiled=compiled)
        return collision_edges(x, graph, self.layout.collision_radius)

    def _inputs(self, history: torch.Tensor, graph: GraphBatch, world: torch.Tensor | None = None,
                turn: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, list[tuple]]:
        """history (N, 3, 3) float64 -> normalised node inputs (N, Fn) float32 and one
        (features, senders, receivers) per edge set: the mesh edges, then (with collisions) the
        collision edges, built from x_t here unless the graph brings them, so that a rollout
        rebuilds them from its own predictions at every step.

        With each object turned to its own heading (`turn`: the cos, sin per node that turned
        the world's `world` into `history`), collision edges are found in the world and their
        vectors turned to the receiving object's heading, the frame its node update reads.
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
            world = history if world is None else world
            c = self.collision_edges(world[:, -1], graph)
            raw = raw_collision_features(world, c, velocity="collision_velocity" in self.collision_normalizers)
            if turn is not None:
                from gns.symmetry import turn_about_z
                for name in COLLISION_VECTORS.intersection(raw):
                    raw[name] = turn_about_z(raw[name], turn[0][c.receivers], turn[1][c.receivers]).to(torch.float32)
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
        """forward with each object turned to its canonical heading (features.canonical_heading):
        about z, so that the mean horizontal velocity of its nodes over the last frame points
        along +x; the acceleration is turned back in scene units (the target normaliser's x and
        y statistics need not match). An object at rest keeps its heading (atan2(0, 0) = 0).
        Per object, not per scene: an object a single-object model meets in a crowded scene is
        then seen as it was trained (the scene's mean heading put each object at another one:
        `movi_a` scored 50% on objects that never met another, 20% on the same objects alone)."""
        own = graph.node_graph
        step = (history[:, -1, :2] - history[:, -2, :2])
        velocity = torch.zeros(graph.num_graphs, 2, dtype=history.dtype, device=history.device).index_add_(0, own, step)
        angle = -torch.atan2(velocity[:, 1], velocity[:, 0])
        cos, sin = torch.cos(angle).index_select(0, own), torch.sin(angle).index_select(0, own)
        from gns.symmetry import turn_about_z
        turned = turn_about_z(history, cos, sin)
        nodes, edge_sets = self._inputs(turned, graph, world=history, turn=(cos, sin))
        out = self.run_network(nodes, *(t for edge_set in edge_sets for t in edge_set))
        acc = self.target_normalizer.inverse(out.to(history.dtype))
        acc = turn_about_z(acc, cos, -sin)   # the turn undone
        return self.target_normalizer(acc).to(torch.float32)

    def set_ensemble(self, members: Sequence["LearnedSimulator"]) -> None:
        """Average every step's predicted acceleration with these models' (an ensemble of runs
        trained apart; each has its own normalisers, speed settings and features of the shared
        graphs). They must read the same graphs (network mesh, floor, collision edges, time step;
        ValueError names the first difference). Features may differ (free flight then waits for
        every member's floor feature: free_flight_clip); with centre nodes, features.surface_edges
        too (gns.ensemble.with_surface_edges rebuilds a member's mesh edges from the faces)."""
        from gns.ensemble import check_members
        check_members(self, members)
        self.__dict__["_members"] = list(members)

    @property
    def members(self) -> list:
        """The ensemble members set by set_ensemble (empty without)."""
        return list(self.__dict__.get("_members") or ())

    def set_contact_model(self, contact: "LearnedSimulator") -> None:
        """Roll out the objects in contact with `contact`, a contact network (gns.contact_network)."""
        check_contact(self, contact)
        self.__dict__["contact_model"] = contact   # kept out of the module tree, as ensemble members are

    def predict_acceleration(self, history: torch.Tensor, graph: GraphBatch) -> torch.Tensor:
        """(N, 3, 3) float64 -> acceleration (N, 3) float64, scene units per frame^2: this model's
        prediction, averaged with its ensemble members' (set_ensemble) if any, each symmetrized
        as this model is asked to be; its contact network's for the objects in contact."""
        if self.contact_model is not None:
            return split_acceleration(self, self.contact_model, history, graph)
        return self._own_acceleration(history, graph)

    def _own_acceleration(self, history: torch.Tensor, graph: GraphBatch) -> torch.Tensor:
        acc = self._predict_one(history, graph, self.symmetrize, self.options.body_frames)
        members = self.__dict__.get("_members")
        if not members:  # the rollout's hot path: no extra tensor work without an ensemble
            return acc
        from gns.ensemble import with_surface_edges
        for m in members:
            own = m._graph_settings["surface_edges"]
            seen = graph if own == self._graph_settings["surface_edges"] else with_surface_edges(graph, own)
            acc = acc + m._predict_one(history, seen, self.symmetrize, self.options.body_frames)
        return acc / (1 + len(members))

    def _predict_one(self, history: torch.Tensor, graph: GraphBatch, symmetrize, body_frames: bool) -> torch.Tensor:
        """This model's acceleration (N, 3) float64, averaged over the images of `symmetrize` (a
        group of gns.symmetry.SYMMETRY_GROUPS, a rollout option) and with `body_frames` over each
        object's equivalent body frames (gns.symmetry.averaged_over_images)."""
        if not symmetrize and not body_frames:
            return self.target_normalizer.inverse(self(history, graph).to(torch.float64))
        from gns.symmetry import averaged_over_images
        return averaged_over_images(self, history, graph, symmetrize, body_frames)

    def network_nodes(self, x_t: torch.Tensor, graph: GraphBatch,
                      graphs: torch.Tensor | None = None) -> tuple[GraphBatch, torch.Tensor] | None:
        """With features.lowest_vertices = k: the graph of each object's k vertices nearest the floor
        at x_t (N, 3) (and its features.highest_vertices highest), its centre and, with collision
        edges, every vertex that has one, and those nodes' indices; None where the network sees
        every node. The cut graph carries the collision edges of the whole one (built there, where
        every face is: surface edges need the other object's triangles): both ends of each are
        kept, so the network sees every contact between objects, however high it is.

        `graphs` (G,) bool: of those graphs only, in one cut, exactly as this on their graph alone
        (gns.graph.select_graphs; its collision edges those between them): a rollout step whose
        network skips some objects. Faces are cut only for an ensemble member that rebuilds its
        mesh edges from them (gns.ensemble.with_surface_edges): nothing else reads them there."""
        if not self.lowest_vertices:
            return None
        keep = lowest_nodes(x_t[:, 2], graph, self.lowest_vertices, self.highest_vertices)
        if self.layout.collisions:
            contacts = self.collision_edges(x_t, graph)
            if graphs is not None and len(contacts.senders):
                own = graph.node_graph
                within = graphs.index_select(0, own.index_select(0, contacts.senders)) & \
                    graphs.index_select(0, own.index_select(0, contacts.receivers))
                contacts = EdgeSet(*(None if e is None else e[within] for e in
                                     (contacts.senders, contacts.receivers, contacts.vectors, contacts.signed)))
            # both ends: a surface edge's sender is a vertex of the other object's nearest triangle
            keep = keep.index_fill(0, contacts.senders, True).index_fill(0, contacts.receivers, True)
            graph = replace(graph, collision_edges=contacts)
        if graph.faces is not None and not self.members:
            graph = replace(graph, faces=None)
        if graphs is None:
            return None if bool(keep.all()) else select_nodes(graph, keep)
        inside = graphs.index_select(0, graph.node_graph)
        keep = keep & inside
        return None if bool(keep.sum() == inside.sum()) else select_graph_nodes(graph, keep, graphs)

    def predict_next(self, x_tm2: torch.Tensor, x_tm1: torch.Tensor, x_t: torch.Tensor,
                     graph: GraphBatch) -> torch.Tensor:
        """Vertex positions (N, 3) float64 at t-2, t-1, t -> positions at t+1 (N, 3) float64.

        With features.lowest_vertices the network moves the nodes it sees (network_nodes) and every
        other vertex takes the pose shape matching fits to those (`fitted_poses`): a rollout's
        shape matching of all of them then finds that same pose."""
        seen = self.network_nodes(x_t, graph)
        if seen is None:
            return self._predict_next(x_tm2, x_tm1, x_t, graph)
        sub, nodes = seen
        return placed_around(self._predict_next(*(f.index_select(0, nodes) for f in (x_tm2, x_tm1, x_t)), sub), seen, graph)

    def fitted_poses(self, x_tm2: torch.Tensor, x_tm1: torch.Tensor, x_t: torch.Tensor, graph: GraphBatch,
                     graphs: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The pose at t+1 that predict_next gives each object, rotations (g, 3, 3) and translations
        (g, 3), of the graphs `graphs` (G,) bool (None: all; as on their graph alone, see
        network_nodes), without placing the vertices the network does not see: a rollout that
        shape-matches every frame poses them itself. None where the network sees every node (the
        positions are then the network's own, not rigid: predict_next)."""
        seen = self.network_nodes(x_t, graph, graphs)
        if seen is None:
            return None
        sub, nodes = seen
        part = self._predict_next(*(f.index_select(0, nodes) for f in (x_tm2, x_tm1, x_t)), sub)
        return fit_packed(part, sub.rest, sub.node_graph, sub.num_graphs)

    def _predict_next(self, x_tm2: torch.Tensor, x_tm1: torch.Tensor, x_t: torch.Tensor, graph: GraphBatch) -> torch.Tensor:
        history = torch.stack([x_tm2, x_tm1, x_t], dim=1)
        return integrate(x_tm1, x_t, self.predict_acceleration(history, graph))

    def loss(self, history: torch.Tensor, target: torch.Tensor, graph: GraphBatch, rigid: float = 0.0,
             next_frame: list | None = None) -> torch.Tensor:
        """Per-node MSE of the normalised acceleration: mean over nodes of the sum over x, y, z.

        history (N, 3, 3) float64 (possibly noisy) inputs; target (N, 3) float64 positions at t+1
        (already corrected for the input noise). The target normaliser accumulates in training.
        rigid > 0 adds rigid x the same loss of the shape-matched prediction against the
        shape-matched target (train.rigid_loss): what a rollout keeps of a step. Shape matching
        runs through the differentiable polar factor (`gns.geometry._rotation_differentiable`).
        `next_frame` (a list) receives predict_next's positions at t+1 from this forward pass,
        detached (pushforward's next input), for a model in training: one network, no symmetries.
        """
        if next_frame is not None and (self.contact_model or self.members or self.symmetrize or self.options.body_frames):
            raise ValueError("next_frame: with a contact network, ensemble or symmetries predict_next is another pass")
        whole, seen = graph, self.network_nodes(history[:, -1], graph)
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
        if next_frame is not None:
            part = integrate(history[:, -2], history[:, -1], self.target_normalizer.inverse(output.detach().double()))
            next_frame.append(part if seen is None else placed_around(part, seen, whole))
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
