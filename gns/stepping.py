"""One rollout step and a rollout: which objects the network moves, which fly free and which
sleep, with shape matching between steps (the symmetries a rollout may average over are
gns.symmetry's).

`Stepping` is the rollout half of gns.simulator.LearnedSimulator (which inherits it): it reads
the model's feature layout, gravity and rollout options (gns.spec.RolloutOptions: shape
matching, free flight and its clearance, sleep) and calls its predict_next.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from gns.network import HISTORY
from gns.geometry import fit_packed, posed, posed_heights, shape_match_packed
from gns.graph import EdgeSet, GraphBatch, alone_in_scenes, per_graph, select_graphs


@dataclass(frozen=True)
class Sleep:
    """Deactivation of resting objects in rollouts, as physics engines do it (Bullet's sleeping).

    A learned model's acceleration at rest is never exactly zero (the small cpu model predicts
    a few % of gravity for an object lying still), and integration turns any such bias into
    drift (docs/results.md). An object sleeps, i.e. keeps its pose, while it lies on the
    floor (lowest vertex within `contact` x its diameter of it) and every vertex moved less than
    `fraction` x |g| dt^2 in both input steps: a tenth of what gravity alone moves a body in
    one frame, which a body in flight cannot do twice in a row (its steps differ by |g| dt^2).
    As in Bullet only a contact wakes it: a collision edge from an object that is awake.
    Objects resting on other objects do not sleep (not handled). Off by default: a rollout
    option (RolloutOptions.sleep, sleep_fraction), not part of the model.
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


def _pose_where(mask: torch.Tensor, a: tuple, b: tuple) -> tuple[torch.Tensor, torch.Tensor]:
    """Per object, pose a (R (G, 3, 3), t (G, 3)) where mask (G,) is True, else pose b."""
    return torch.where(mask[:, None, None], a[0], b[0]), torch.where(mask[:, None], a[1], b[1])


class Stepping:
    """The rollout methods of LearnedSimulator (see the module docstring)."""

    @property
    def free_flight_clip(self) -> float:
        """How far above the floor an object must stay to be in free flight: the largest floor
        clip of this model and its ensemble members (beyond it no member's network sees the floor,
        so the exact update is what the network would approximate), or the options' free_clearance
        if set.
        A clearance below the clip also takes the band where the network sees the floor but no
        vertex can reach it within the step (now or after the ballistic step): fewer object-steps
        in the network, at an accuracy measured in experiments/log.md."""
        if self.options.free_clearance is not None:
            return float(self.options.free_clearance)
        return max([self.layout.floor_clip] + [m.layout.floor_clip for m in self.members])

    @property
    def sleep(self) -> Sleep | None:
        """The deactivation of resting objects the options ask for (None: off)."""
        return Sleep(self.options.sleep_fraction) if self.options.sleep else None

    def in_free_flight(self, frames: list[torch.Tensor], ballistic: torch.Tensor, graph: GraphBatch,
                       contacts: EdgeSet | None) -> torch.Tensor:
        """(G,) objects out of reach of the floor and of every other object for the whole step:
        every vertex at least the floor feature's clip above the floor both now and after the
        ballistic step (`ballistic`, (N, 3) at t+1; its heights (N,) do without other objects in
        its scenes), so the network sees no floor; no collision
        edge now; and no other object's box, swept over the last and the next step, within the
        collision radius of its own swept box, so none can appear. The network's answer for such
        an object depends on its own motion only: its learned free flight, which the exact
        inertial update replaces. (Free only at t measured 25.9% position against 29.0% with the
        network everywhere on MOVi-A, but penetration 0.38% against 0.29%: an object one step
        from the floor had been moved into it; experiments/log.md.)"""
        x = frames[-1]
        free = torch.ones(graph.num_graphs, dtype=torch.bool, device=x.device)
        if self.layout.floor_z is not None:
            clear = self.layout.floor_z + self.free_flight_clip
            heights = ballistic if ballistic.dim() == 1 else ballistic[:, 2]
            free &= (per_graph(x[:, 2], graph, "amin") >= clear) & (per_graph(heights, graph, "amin") >= clear)
        if self.layout.collisions:
            if contacts is not None and len(contacts.senders):
                free[graph.node_graph[contacts.senders]] = False
            if graph.graph_scene is not None and graph.num_graphs > 1:
                # each object's box swept over x_{t-1}, x_t and the ballistic x_{t+1}: a pair whose
                # swept boxes come within the collision radius may touch during the step
                swept = torch.stack([frames[-2], x, ballistic])
                low = per_graph(swept.amin(0), graph, "amin")
                high = per_graph(swept.amax(0), graph, "amax")
                from gns.contacts import candidate_pairs
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

    def advance(self, frames: list[torch.Tensor], graph: GraphBatch, pose: list | None = None,
                counts: dict | None = None, fitted: list | None = None,
                live: torch.Tensor | None = None) -> torch.Tensor | None:
        """One rollout step: positions (N, 3) at t+1 from frames [..., x_{t-2}, x_{t-1}, x_t], before
        shape matching. Sleeping objects keep x_t, free ones (options.free_flight; `pose` holds the
        (R, t) of the last two frames) take the inertial update, the rest the network's answer.
        `counts` (if given) adds this step's object-steps: in the network, free, asleep. With
        `fitted` (a list) and free flight, a model with features.lowest_vertices whose network
        sees a cut of the graph appends every object's pose at t+1, (R (G, 3, 3), t (G, 3)),
        which shape matching the positions would find (the pose fitted to the network's nodes,
        the ballistic one, the one kept), if rigid frames were given, and returns None: the
        caller (a rollout, which shape-matches every frame) poses the vertices; placing them
        here too cost ~5% of a MOVi-A rollout's step. `live` (G,) bool: the objects whose step
        counts and moves; the others (a batch's ended tracks) are held where they are; None: all."""
        sleep, free_flight = self.sleep, self.options.free_flight
        counts = {} if counts is None else counts
        for key in ("object_steps", "network", "free_flight", "asleep"):
            counts.setdefault(key, 0)

        def counted(mask: torch.Tensor | None = None) -> int:
            """Object-steps of the objects in mask (None: all), live ones only."""
            if mask is None:
                return graph.num_graphs if live is None else int(live.sum())
            return int((mask if live is None else mask & live).sum())
        if free_flight and pose is None:
            pose = [fit_packed(f, graph.rest, graph.node_graph, graph.num_graphs) for f in frames[-2:]]
        step_graph, contacts = graph, None
        if self.layout.collisions and (sleep is not None or free_flight):
            # built once from x_t: the network, the wake-up and the free-flight tests share them
            contacts = self.collision_edges(frames[-1], graph)
            step_graph = replace(graph, collision_edges=contacts)
        # an object past its track's end is padding: held where it is, like a sleeping one, so a
        # batch of ragged tracks computes only what is live (72% of real-cube steps were padding)
        skip = torch.zeros(graph.num_graphs, dtype=torch.bool, device=frames[-1].device) if live is None else ~live
        if sleep is not None:
            sleeping = sleep.asleep_graphs(frames, graph, self.gravity_step, self.layout.floor_z, contacts)
            counts["asleep"] += counted(sleeping)
            skip |= sleeping
        poses_only = fitted is not None and free_flight and bool(self.lowest_vertices)
        if free_flight:
            flight = self.inertial_pose(*pose)
            # handing over poses, the free-flight test reads the ballistic heights alone, unless
            # other objects' boxes are swept too (in_free_flight)
            heights = poses_only and not (self.layout.collisions and graph.graph_scene is not None
                                          and graph.num_graphs > 1)
            ballistic = (posed_heights if heights else posed)(*flight, graph.node_graph, graph.rest)
            free = self.in_free_flight(frames, ballistic, graph, contacts) & ~skip
            counts["free_flight"] += counted(free)
            skip |= free
        counts["object_steps"] += counted()
        skip_node = skip[graph.node_graph]
        needed = None   # the graphs of the network call; None: all
        if int(skip_node.sum()) >= SUBGRAPH_MIN_SHARE * graph.num_nodes:
            needed = ~skip
            if contacts is not None and len(contacts.senders):
                # a skipped object whose vertices an active one feels (a sleeper touching a
                # woken one) enters the call too, so the active one's answer is unchanged
                feeds = needed[graph.node_graph[contacts.receivers]]
                needed = needed.clone()
                needed[graph.node_graph[contacts.senders[feeds]]] = True
        # else few to leave out: one call on everything is cheaper than cutting the graph, and
        # the others' answers are the same (a skipped object shares no edge with them)
        if poses_only:
            held_pose = _pose_where(free, flight, pose[1])   # the ballistic one, or the one at t
            if needed is not None and not needed.any():
                fitted.append(held_pose)
                return None
            fit = self.fitted_poses(*frames[-HISTORY:], step_graph, needed)
            if fit is not None:
                counts["network"] += counted(needed)
                if needed is None:
                    fitted.append(_pose_where(skip, held_pose, fit))
                else:
                    graphs = needed.nonzero()[:, 0]
                    kept = ~skip[graphs]
                    fitted.append(tuple(h.index_put((graphs[kept],), a[kept]) for a, h in zip(fit, held_pose)))
                return None
            if heights:   # the network sees every node: its positions, not a pose (predict_next)
                ballistic = posed(*flight, graph.node_graph, graph.rest)
        # where a skipped object goes: free ones fly, sleeping ones keep their pose
        held = torch.where(free[graph.node_graph, None], ballistic, frames[-1]) if free_flight else frames[-1]
        if needed is None:
            x = self.predict_next(*frames[-HISTORY:], step_graph)
            counts["network"] += counted()
            if skip.any():
                x = torch.where(skip_node[:, None], held, x)
            return x
        x = held
        if needed.any():
            sub, nodes = select_graphs(step_graph, needed)
            pred = self.predict_next(*(f[nodes] for f in frames[-HISTORY:]), sub)
            use = ~skip[graph.node_graph[nodes]]
            x = x.index_put((nodes[use],), pred[use])  # out of place: gradients pass
            counts["network"] += counted(needed)
        return x

    def keep_apart(self, x: torch.Tensor, frames: list, graph: GraphBatch, pose: list | None = None):
        """The rollout option keep_apart after a step: the objects of a scene translated out of each
        other (gns.contacts.separation). For a model with collision edges, whose network is the
        contact's response, the frames the next step reads besides the pushed one (the last
        HISTORY - 1) and the free-flight pose of the newest of them move with the push too: the
        finite differences the network and free flight read see no push, as Bullet's split impulse
        corrects penetration apart from the velocities (2-4 points better in crowds, log
        2026-12-07). For a model without them the push is the only response, so it is left in the
        velocity (the objects part at the push's speed); kept out of it, objects driven into each
        other step after step go through. Returns (x, frames, pose, the push (G, 3))."""
        from gns.contacts import separation
        shift = separation(x, graph, self.layout.floor_z)
        node_shift = shift[graph.node_graph]
        if self.layout.collisions:
            frames = frames[:-(HISTORY - 1)] + [f + node_shift for f in frames[-(HISTORY - 1):]]
            if pose is not None:
                pose = [pose[0], (pose[1][0], pose[1][1] + shift)]
        return x + node_shift, frames, pose, shift

    @torch.no_grad()
    def rollout(self, history: torch.Tensor, graph: GraphBatch, steps: int, poses: bool = False,
                live_steps: torch.Tensor | None = None):
        """Run on its own predictions from history (N, 3, 3) float64 -> positions (steps, N, 3),
        as the model's rollout options ask.

        With shape_matching, each prediction is replaced by the rigid projection of the rest mesh
        before it enters the history (paper, rollouts only). With `sleep`, objects at rest keep
        their pose until the model predicts a real acceleration (see Sleep). With `free_flight`,
        objects out of reach of the floor and of every other object (`in_free_flight`) follow the
        exact inertial update (`inertial_pose`) instead of the network, and only the others enter
        the network call; sleeping objects do not enter it either. With `keep_apart`, objects of a
        scene that overlap after the step are translated apart (gns.contacts.separation) before the
        step enters the history; with collision edges, so are the frames before it that the next
        step reads, so the push gives no velocity (`keep_apart`). `self.rollout_counts` then says
        how many object-steps did. With `poses`, also returns every predicted frame's pose from
        shape matching, rotations (steps, G, 3, 3) and translations (steps, G, 3). `live_steps`
        (G,): how many of the steps are each object's own (its track's length), the rest padding:
        an object past them is held still and left out of the network call and the counts.
        """
        shape_matching, sleep, free_flight = self.options.shape_matching, self.sleep, self.options.free_flight
        if graph.graph_scene is not None and graph.num_graphs > 1 and alone_in_scenes(graph):
            # every object alone in its scene is what no grouping means: no collision edge, swept
            # box or overlap to look for at each step (a fifth of a multi-object model's step on
            # single-object scenes went to finding none)
            graph = replace(graph, graph_scene=None)
        keep_apart = self.options.keep_apart and graph.graph_scene is not None and graph.num_graphs > 1
        if sleep is not None and not self.gravity_step:
            raise ValueError("sleeping needs the model's gravity and frame rate (spec)")
        if free_flight and self.gravity_per_frame is None:
            raise ValueError("free flight needs the model's gravity and frame rate (spec)")
        if self.options.body_frames and graph.symmetries is None:
            from gns.symmetry import with_symmetries
            graph = with_symmetries(graph)
        frames = list(history.unbind(1))
        pose = [fit_packed(f, graph.rest, graph.node_graph, graph.num_graphs) for f in frames[-2:]] \
            if free_flight else None
        out, rots, trans = [], [], []
        counts = {"object_steps": 0, "network": 0, "free_flight": 0, "asleep": 0}
        for k in range(steps):
            # with shape matching every frame is rigid, and a model that fits poses to a few
            # nodes (features.lowest_vertices) hands them over: no second fit of all nodes
            fitted = [] if shape_matching and free_flight and self.lowest_vertices else None
            x = self.advance(frames, graph, pose, counts, fitted, None if live_steps is None else live_steps > k)
            if fitted:
                rot, t = fitted[0]
                matched = posed(rot, t, graph.node_graph, graph.rest)
            elif shape_matching or poses or free_flight:
                rot, t, matched = shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)
            if shape_matching or poses or free_flight:
                if shape_matching:
                    x = matched
                if keep_apart:
                    x, frames, pose, shift = self.keep_apart(x, frames, graph, pose)
                    t = t + shift
                if poses:
                    rots.append(rot)
                    trans.append(t)
                if free_flight:
                    pose = [pose[1], (rot, t)]
            elif keep_apart:
                x, frames, _, _ = self.keep_apart(x, frames, graph)
            frames.append(x)
            out.append(x)
        self.rollout_counts = counts
        if poses:
            return torch.stack(out), torch.stack(rots), torch.stack(trans)
        return torch.stack(out)
