"""Use a trained model from Python: load it, roll it out from poses and velocities, step it in a loop.

    import gns
    model = gns.load("real_cubes")   # a zoo name, a run folder or a .pt file
    out = model.rollout(shapes=["cube"], scales=2.0, positions=[[0, 0, 3]], quaternions=[[1, 0, 0, 0]],
                        velocities=[[5, 0, 0]], angular_velocities=[[0, 0, 3]], steps=40)
    out.positions, out.quaternions                   # (steps + 1, B, 3), (steps + 1, B, 4); [0] is the start

Conventions (those of the data format, docs/data_format.md): quaternions w x y z, body to
world (`quaternion_order="xyzw"` at load for scipy's order, used for inputs and outputs alike);
velocities in scene units per second and angular velocities in radians per second, both in
the world frame; object i's vertices are R(q_i) (scales_i * mesh vertices) + positions_i.

The model reads vertex positions at 3 frames t - 2 dt, t - dt, t. From a pose and velocity at t
they are extrapolated back in free flight, as a recorded toss would have them:
x(t - s) = x - v s + g s^2 / 2 for the centre and R(t - s) = exp(-[w] s) R for the rotation
(constant world angular velocity), s = dt, 2 dt. An object in contact during those two frames
has no such history; give its true past poses through `history` instead.

All objects given to one call form ONE scene (they can collide) unless `scene` groups them
into independent scenes, which are rolled out batched in one network call per step.
"""
from __future__ import annotations

import numbers
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from plumbing import DataError
from gns.config import Config, ConfigError, build_config
from gns.network import HISTORY
from gns.graph import GraphBatch
from gns.symmetry import with_symmetries
from gns.spec import outside_training
from gns import api_inputs as inputs
from gns.geometry import posed, shape_match_packed
from gns.simulator import LearnedSimulator
from gns.spec import ModelSpec
from gns.checkpoint import CheckpointError, checkpoint_of, load_simulator, parse_device
from gns.spec import RolloutOptions
from gns.checkpoint import default_options


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz, normalised first -> (..., 3, 3); differentiable, on q's device."""
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 4) unit wxyz with w >= 0: Shepperd's method (as
    gns.geometry.matrix_to_quat), every candidate computed and the best-conditioned one taken."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    cands = torch.stack([
        torch.stack([1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22], -1),
    ], -2)
    pick = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1).argmax(-1)
    q = cands.gather(-2, pick[..., None, None].expand(*pick.shape, 1, 4))[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


def rotation_vector_to_matrix(r: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis x angle -> (..., 3, 3), Rodrigues; exact (and differentiable) at zero angle too."""
    angle = r.norm(dim=-1, keepdim=True)
    small = angle < 1e-8
    safe = torch.where(small, torch.ones_like(angle), angle)
    half = 0.5 * safe
    # sin(a/2)/a -> 1/2 and cos(a/2) -> 1 at zero, without dividing by it
    s = torch.where(small, 0.5 - angle ** 2 / 48, torch.sin(half) / safe)
    c = torch.where(small, 1 - angle ** 2 / 8, torch.cos(half))
    return quat_to_matrix(torch.cat([c, s * r], -1))


def history_poses(positions: torch.Tensor, rotations: torch.Tensor, velocities: torch.Tensor,
                  angular_velocities: torch.Tensor, dt: float, gravity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres (3, B, 3) and rotations (3, B, 3, 3) at t - 2 dt, t - dt, t from the pose and
    velocity at t, in free flight: x(t - s) = x - v s + g s^2 / 2, R(t - s) = exp(-[w] s) R."""
    pos, rot = [], []
    for k in range(HISTORY - 1, -1, -1):
        s = k * dt
        pos.append(positions - velocities * s + 0.5 * gravity * s * s)
        rot.append(rotation_vector_to_matrix(-angular_velocities * s) @ rotations)
    return torch.stack(pos), torch.stack(rot)


@dataclass
class State:
    """Where a rollout is: the model's 3 input frames of vertex positions and the current poses."""

    positions: torch.Tensor        # (B, 3) centres at the current frame
    quaternions: torch.Tensor      # (B, 4) in the model's quaternion_order
    vertices: torch.Tensor         # (N, 3) world vertices of the meshes (with a centre node each where the model has one); object of each: vertex_object
    time: float                    # seconds since the first state
    frames: tuple[torch.Tensor, ...] = field(repr=False)   # HISTORY x (N, 3) float64, oldest first
    graph: GraphBatch = field(repr=False)

    @property
    def vertex_object(self) -> torch.Tensor:
        """(N,) the object (index into the inputs) of each vertex."""
        return self.graph.node_graph


@dataclass
class Trajectory:
    """A rollout: frame k is at time k * dt; frame 0 is the given state."""

    positions: torch.Tensor        # (steps + 1, B, 3)
    quaternions: torch.Tensor      # (steps + 1, B, 4) in the model's quaternion_order, sign continuous
    vertices: torch.Tensor         # (steps + 1, N, 3)
    vertex_object: torch.Tensor    # (N,)
    dt: float
    scales: torch.Tensor | None = None   # (B,) the objects' scales, for Model.every_frame

    @property
    def times(self) -> torch.Tensor:
        return torch.arange(self.positions.shape[0], dtype=torch.float64) * self.dt


class Model:
    """A trained simulator with what using it needs: meshes, time step, gravity, training ranges."""

    def __init__(self, simulator: LearnedSimulator, config: Config, spec: ModelSpec, meshes: dict,
                 device: torch.device, quaternion_order: str = "wxyz", source: str = "", between: dict | None = None):
        if quaternion_order not in ("wxyz", "xyzw"):
            raise ConfigError(f"quaternion_order must be 'wxyz' or 'xyzw', got {quaternion_order!r}")
        self.simulator, self.config, self.spec, self.device = simulator, config, spec, device
        self.quaternion_order, self.source = quaternion_order, source
        self._between = between   # the file's reader between steps (gns.between), if it holds one
        self.meshes = meshes
        # the graphs the network was trained on (centre nodes, spokes)
        self._library = simulator.mesh_library(meshes)

    frame_rate = property(lambda self: float(self.spec.frame_rate), doc="model steps per second")
    dt = property(lambda self: 1.0 / self.frame_rate, doc="seconds per step (the data's frame time x frame_stride)")
    frame_stride = property(lambda self: self.config.features.frame_stride,
                            doc="recorded frames per model step in training")
    gravity = property(lambda self: np.asarray(self.spec.gravity, np.float64), doc="(3,) scene units / s^2")
    floor = property(lambda self: None if self.spec.floor is None else self.spec.floor.to_dict(),
                     doc="{'z', ...} or None")
    shapes = property(lambda self: list(self.spec.shapes), doc="shapes seen in training")
    ranges = property(lambda self: {k: [lo, hi] for k, (lo, hi) in self.spec.ranges.items()},
                      doc="[min, max] of what training saw")
    uses_materials = property(lambda self: self.spec.materials_vary,
                              doc="friction and restitution are inputs (they varied in training)")
    collisions = property(lambda self: self.spec.collision_edges,
                          doc="objects of a scene interact (collision edges)")
    options = property(lambda self: self.simulator.options, doc="how it rolls out (gns.spec.RolloutOptions)")

    def __repr__(self) -> str:
        return (f"gns.Model({self.source!r}, {self.frame_rate:g} steps/s, shapes {self.shapes}, "
                f"materials {'yes' if self.uses_materials else 'no'}, collisions {'yes' if self.collisions else 'no'}"
                f"{' and a contact network' if self.simulator.contact_model is not None else ''}, "
                f"device {self.device})")

    def _quat_in(self, q: torch.Tensor) -> torch.Tensor:
        return q[..., [3, 0, 1, 2]] if self.quaternion_order == "xyzw" else q

    def _quat_out(self, q: torch.Tensor) -> torch.Tensor:
        return q[..., [1, 2, 3, 0]] if self.quaternion_order == "xyzw" else q

    def state(self, shapes: list[str], positions, quaternions, velocities=None, angular_velocities=None, *,
              scales=1.0, friction=None, restitution=None, scene=None, history=None, warn: bool = True,
              _caller_depth: int = 0) -> State:
        """The start of a rollout: B objects, one row each.

        shapes: B mesh names (model.meshes); positions (B, 3); quaternions (B, 4); velocities and
        angular_velocities (B, 3) world frame, per second (default 0); scales, friction,
        restitution: one value or (B,) (friction and restitution are needed, and used, only
        when model.uses_materials); scene: (B,) ints, objects with the same number interact
        (default: all one scene). history: instead of velocities, the true poses at t - 2 dt and
        t - dt as (positions (2, B, 3), quaternions (2, B, 4)). Tensors that require grad keep
        their graph (rollout(differentiable=True)). Bad input is one DataError naming it
        (gns.api_inputs): None, text or ragged rows, one row for several objects, a value that
        is not finite, a size <= 0, friction < 0, restitution outside [0, 1], a zero quaternion,
        an object starting below the floor, a spin of pi / dt or more; objects starting inside
        each other are warned about."""
        dev = self.device
        # every input checked (finite, one row per object, physical) before any is used: gns.api_inputs
        shapes = inputs.shape_names(shapes, self.meshes)
        b = len(shapes)
        pos = inputs.rows(positions, "positions", b, 3, dev)
        quat = self._quat_in(inputs.quaternions(quaternions, "quaternions", b, dev))
        scale = inputs.per_object(scales, "scales", b, dev, inputs.positive)
        mat = self._materials(friction, restitution, b)
        group = inputs.scene_numbers(scene, b, dev)
        rot = quat_to_matrix(quat)
        if history is None:
            zero = torch.zeros(b, 3, dtype=torch.float64, device=dev)
            vel = zero if velocities is None else inputs.rows(velocities, "velocities", b, 3, dev)
            ang = zero if angular_velocities is None else inputs.rows(angular_velocities, "angular_velocities", b, 3, dev)
            inputs.check_spin(ang, self.dt)
            g = torch.as_tensor(self.gravity, dtype=torch.float64, device=dev)
            past_pos, past_rot = history_poses(pos, rot, vel, ang, self.dt, g)
            spin, given = ang.detach().norm(dim=-1), [HISTORY - 1]   # the true speed (the frames show it up to pi / dt)
        else:
            if velocities is not None or angular_velocities is not None:
                raise DataError("give either velocities or history, not both")
            hp, hq = inputs.history_pair(history, b)
            hp = inputs.rows(hp, "history positions", b, 3, dev, frames=HISTORY - 1)
            hq = self._quat_in(inputs.quaternions(hq, "history quaternions", b, dev, frames=HISTORY - 1))
            past_pos, past_rot = torch.cat([hp, pos[None]]), torch.cat([quat_to_matrix(hq), rot[None]])
            spin, given = None, list(range(HISTORY))
        cpu = lambda t: t.detach().cpu()  # noqa: E731  packing indexes the library on the CPU
        ones = torch.ones(b, dtype=torch.float64, device="cpu")
        graph = self._library.pack(self._library.shape_ids(shapes), ones, cpu(mat[0]), cpu(mat[1]), cpu(group)).to(dev)
        # scaled rest shape and materials from the inputs themselves, so that a gradient reaches them
        graph.rest = graph.rest * scale[graph.node_graph, None]
        graph.material = torch.stack(mat, 1).to(torch.float32)[graph.node_graph]
        if self.simulator.options.body_frames:
            # the rotations mapping each mesh onto itself, which every step averages over
            graph = with_symmetries(graph)
        frames = tuple(posed(past_rot[k], past_pos[k], graph.node_graph, graph.rest) for k in range(HISTORY))
        inputs.check_floor(frames, graph.node_graph, scale, shapes, self.spec.floor_z, given)
        if warn:
            self._warn_outside(shapes, past_pos, past_rot, scale, mat, group, 3 + _caller_depth, spin)
            overlap = inputs.overlap_warning(shapes, self.meshes, pos, scale, group, self.collisions)
            if overlap:
                warnings.warn(overlap, stacklevel=2 + _caller_depth)
        return State(pos, self._quat_out(quat / quat.norm(dim=-1, keepdim=True)), frames[-1], 0.0, frames, graph)

    def _materials(self, friction, restitution, b: int) -> tuple[torch.Tensor, torch.Tensor]:
        if self.uses_materials and (friction is None or restitution is None):
            lo_f, hi_f = self.ranges["friction"]
            lo_r, hi_r = self.ranges["restitution"]
            raise DataError(f"this model takes each object's material: give friction= and restitution= "
                            f"(trained on {lo_f:g} to {hi_f:g} and {lo_r:g} to {hi_r:g})")
        # a model without material inputs never reads them; the training value is kept for the record
        f = inputs.per_object(self.ranges["friction"][0] if friction is None else friction, "friction", b,
                              self.device, inputs.non_negative)
        r = inputs.per_object(self.ranges["restitution"][0] if restitution is None else restitution, "restitution", b,
                              self.device, inputs.unit_interval)
        return f, r

    def _warn_outside(self, shapes, past_pos, past_rot, scale, mat, group, stacklevel: int, spin=None) -> None:
        """One UserWarning per input outside the training ranges, attributed to the user's line.
        spin: the true angular speeds (B,) where known (given velocities), else the rotation
        between the last two frames gives them."""
        p = past_pos.detach().cpu().numpy()
        speed = np.linalg.norm(p[-1] - p[-2], axis=-1) * self.frame_rate
        if spin is not None:
            angle = spin.cpu().numpy()
        else:   # the angle of the relative rotation, from its trace and skew part (no SVD to fail)
            rel = (past_rot[-1] @ past_rot[-2].transpose(-1, -2)).detach().cpu().numpy()
            skew = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
            angle = np.arctan2(np.linalg.norm(skew, axis=-1), np.trace(rel, axis1=-2, axis2=-1) - 1) * self.frame_rate
        span = lambda a: (float(np.min(a)), float(np.max(a)))  # noqa: E731
        ranges = {"speed": span(speed), "angular_speed": span(angle), "height": span(p[..., 2]),
                  "scale": span(scale.detach().cpu().numpy())}
        if self.uses_materials:
            ranges.update(friction=span(mat[0].detach().cpu().numpy()), restitution=span(mat[1].detach().cpu().numpy()))
        # the inputs' frame rate, gravity and floor are the model's own
        data = replace(self.spec, shapes=tuple(sorted(set(shapes))), ranges=ranges)
        for problem in outside_training(self.spec, data):
            warnings.warn(f"outside training: {problem}", stacklevel=stacklevel)
        if not self.collisions and len(torch.unique(group)) < len(shapes):
            warnings.warn("the model was trained on single-object scenes and has no collision edges: "
                          "objects of one scene will pass through each other unless keep_apart=True translates them apart "
                          "(a projection, not learned contact)", stacklevel=stacklevel)

    def step(self, state: State) -> State:
        """The state one model step (dt) later, as the model's options ask (`options`, set by
        gns.load: e.g. free_flight, objects out of reach of the floor and of each other following
        the exact inertial update, not the network). Keeps the autograd graph when grad is enabled
        (wrap a loop in torch.no_grad() otherwise)."""
        if not isinstance(state, State):
            raise TypeError(f"step() takes the State of model.state(...) or of an earlier step, got {type(state).__name__}")
        sim, graph = self.simulator, state.graph
        if sim.options.free_flight and sim.gravity_per_frame is None:
            raise DataError("free_flight needs a model that knows gravity and its frame rate")
        if sim.options.sleep and not sim.gravity_step:
            raise DataError("sleep needs a model that knows gravity and its frame rate")
        frames = list(state.frames)
        x = sim.advance(frames, graph)
        rot, centre, matched = shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)
        if sim.options.shape_matching:
            x = matched
        if sim.options.keep_apart and graph.graph_scene is not None and graph.num_graphs > 1:
            # as rollouts keep objects apart (Stepping.keep_apart: the push and the frames it moves)
            x, frames, _, shift = sim.keep_apart(x, frames, graph)
            centre = centre + shift
        quat = matrix_to_quat(rot)
        previous = self._quat_in(state.quaternions)
        # the cover nearest the previous frame's, so that quaternions are continuous in time
        quat = quat * torch.where((quat * previous).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        return State(centre, self._quat_out(quat), x, state.time + self.dt, (*frames[1:], x), graph)

    def rollout(self, shapes: list[str], positions, quaternions, velocities=None, angular_velocities=None, *,
                steps: int, scales=1.0, friction=None, restitution=None, scene=None, history=None,
                differentiable: bool = False) -> Trajectory:
        """Roll B objects out for `steps` model steps (arguments as `state`), as `step` does.
        differentiable=True keeps the autograd graph from the inputs (tensors with requires_grad)
        to every output."""
        if not isinstance(steps, numbers.Integral) or steps < 0:
            raise DataError(f"steps must be a whole number >= 0, got {steps!r}")
        with torch.set_grad_enabled(differentiable):
            state = self.state(shapes, positions, quaternions, velocities, angular_velocities, scales=scales,
                               friction=friction, restitution=restitution, scene=scene, history=history,
                               _caller_depth=1)
            states = [state]
            for _ in range(steps):
                states.append(self.step(states[-1]))
            scale = torch.as_tensor(scales, dtype=torch.float64).detach().reshape(-1).expand(len(shapes)).clone()
            return Trajectory(torch.stack([s.positions for s in states]), torch.stack([s.quaternions for s in states]),
                              torch.stack([s.vertices for s in states]), state.vertex_object, self.dt, scale)

    def every_frame(self, trajectory: Trajectory, between: str = "learned") -> tuple[torch.Tensor, torch.Tensor, float]:
        """A rollout of a model that steps k recorded frames (frame_stride k > 1; real_cubes' k is 8)
        read at every recorded frame, as `gns eval --at-data-rate` scores it: by the reader between
        steps the model file holds (gns export --between), else, or with between="spline", a cubic
        spline through the centres and slerp between the orientations. Returns the centres
        ((T - 1) k + 1, B, 3), the quaternions (.., B, 4, this model's order) and their frame time
        dt / k; the model's own frames are kept."""
        from gns.at_data_rate import reader_of, read_every_frame
        k = int(self.frame_stride)
        if trajectory.scales is None:
            raise DataError("this trajectory has no scales: every_frame reads a Model.rollout's")
        reader = reader_of({"between": self._between}, between) if k > 1 else None
        q = self._quat_in(trajectory.quaternions.detach()).cpu().numpy().astype(np.float64)
        positions, quats = read_every_frame(trajectory.positions.detach().cpu().numpy().astype(np.float64), q,
                                            trajectory.scales.cpu().numpy(), k, reader)
        quats = self._quat_out(torch.from_numpy(quats))
        return torch.from_numpy(positions), quats, trajectory.dt / k


def _meshes_of(spec: ModelSpec, where: str) -> dict:
    """The checkpoint's meshes; a checkpoint written before they were kept names its shapes,
    which are looked up among datagen's shapes."""
    if spec.meshes:
        return {name: (v.numpy(), f.numpy()) for name, (v, f) in spec.meshes.items()}
    from datagen.scenes import SHAPES, get_shape
    unknown = [s for s in spec.shapes if s not in SHAPES]
    if unknown:
        raise CheckpointError(f"{where} holds no meshes (written before they were kept) and its shape "
                              f"{unknown[0]!r} is not one of datagen's ({', '.join(SHAPES)}); pass meshes={{name: "
                              f"(vertices, faces)}} to gns.load")
    return {name: (get_shape(name).vertices, get_shape(name).faces) for name in spec.shapes}


def load(model: str | Path, device: str | torch.device = "cpu", quaternion_order: str = "wxyz",
         meshes: dict | None = None, options: RolloutOptions | None = None, **changes) -> Model:
    """A trained model: a zoo name (`gns models` lists them), a run folder (its latest.pt) or a
    .pt checkpoint or export. device: "cpu", "cuda", "cuda:1", ... meshes {name: (vertices,
    faces)} replaces the checkpoint's (needed only for old checkpoints of custom shapes).
    options: how it rolls out (gns.spec.RolloutOptions; default gns.checkpoint.default_options(model),
    for a zoo model the options it was scored with). Keywords (RolloutOptions fields) change those
    options, e.g. free_flight=True, sleep=True or autocast="auto"; symmetrize True or "d2"
    averages each step over the floor's mirror images (`gns eval --symmetrize`; four network
    calls a step), rollouts exactly
    mirror-equivariant as far as the mesh graph is (a cube's triangulated faces are not quite),
    or another group of gns.symmetry.SYMMETRY_GROUPS ("none": off); ensemble: more models (names,
    folders, files) whose predictions each step averages with this one's (`gns eval --ensemble`);
    they must read the same graphs."""
    device = parse_device(str(device), "device")
    ensemble = changes.get("ensemble")
    if ensemble is not None:
        changes["ensemble"] = (str(ensemble),) if isinstance(ensemble, (str, Path)) else tuple(str(e) for e in ensemble)
    known = set(RolloutOptions.__dataclass_fields__)
    unknown = sorted(set(changes) - known)
    if unknown:   # a misspelt option: one line naming the known ones, not a TypeError from dataclasses
        raise TypeError(f"gns.load() got an unknown rollout option {unknown[0]!r}; known: {', '.join(sorted(known))}")
    options = (default_options(model) if options is None else options).replace(**changes)
    path = checkpoint_of(model)
    sim, ckpt = load_simulator(path, device, options)
    cfg = build_config(base=ckpt["config"])
    spec = ModelSpec.from_dict(ckpt["spec"])
    found = meshes if meshes is not None else _meshes_of(spec, str(path))
    return Model(sim, cfg, spec, {k: (np.asarray(v, np.float64), np.asarray(f, np.int64))
                                         for k, (v, f) in found.items()}, device, quaternion_order, str(model),
                 between=ckpt.get("between"))
