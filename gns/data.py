"""Training windows from the shards: poses in memory, vertex positions built per batch.

A *track* is one object through one scene. A *window* is 3 input frames (t-2, t-1, t) and the
target frame t+1 of one scene: one graph per object of the scene, packed together and marked as
one scene (`GraphBatch.graph_scene`) so that collision edges can join them. With one object per
scene a window is one track and one graph. Memory holds only the poses
(positions and quaternions, float64) and the meshes once; vertex positions are computed for the
windows of a batch, vectorised, as R(q) (scale * rest) + p.

Augmentation (training only):
- rotation of inputs and target about the world z axis by theta ~ U[-pi, pi], one per window
  (all objects of a scene rotate together, about the same axis);
- mirror (`augment.mirror`): half the windows mirrored in x, world and body frame together
  (x = R r + p -> M x = (M R M)(M r) + M p, M = diag(-1, 1, 1)): the mirror image of a scene is
  a scene of the mirrored object under the same physics, and the pose stays a proper rotation.
  With the z rotation this covers every vertical mirror plane;
- body symmetry (`augment.body_symmetry`): each object's rest positions described in another of
  its mesh's equivalent body frames (r -> S r, R -> R S^T, S a rotation mapping the mesh's
  vertices onto themselves, gns.graph.mesh_symmetries): the world vertices are unchanged, only
  the labels move, so the model learns that a cube's answer does not hang on which of its 24
  frames describes it (docs/results.md);
- random-walk position noise as in learning_to_simulate: per node, each input velocity gets
  N(0, noise_std^2 / 2) noise, accumulated over the history, so the last input frame carries
  noise of std noise_std. The target position is shifted by the last frame's noise, so the
  target acceleration x_{t+1} - 2 x_t + x_{t-1} asks the model to undo the noise of the last
  input velocity.
Noise of the paper's robustness study (Fig. 7), off by default. It makes the training data
themselves noisy, target included, and nothing corrects for it:
- vertex_noise (imperfect shape): one Gaussian offset per vertex, in the body frame, std =
  vertex_noise x the object's size (largest extent of its scaled rest mesh), the same in the
  4 frames of a window, so the object moves rigidly with a distorted shape;
- track_noise (imperfect tracking): Gaussian noise on the centre at every frame of the window,
  independently, std = track_noise x the centre's displacement at that frame (from the frame
  before; the first frame uses the next step), added to the pose before vertices are built.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from datagen.shards import Dataset, Scene
from gns.config import Config, ConfigError
from plumbing import DataError
from gns.network import HISTORY
from gns.geometry import quat_to_matrix, rotation_angle
from gns.graph import GraphBatch, MeshLibrary, graph_settings, graph_sizes, ragged_arange
from gns.spec import Floor, ModelSpec, SpecError


def rotation_z(theta: torch.Tensor) -> torch.Tensor:
    """Angles (B,) -> rotations about +z (B, 3, 3)."""
    c, s = theta.cos(), theta.sin()
    zero, one = torch.zeros_like(theta), torch.ones_like(theta)
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).reshape(-1, 3, 3)


def vertices_from_poses(graph: GraphBatch, positions: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """World vertices R (rest) + p for every node and frame.

    positions (B, T, 3), rotations (B, T, 3, 3) per graph of `graph` -> (N, T, 3) float64.
    """
    rot = rotations[graph.node_graph]                        # (N, T, 3, 3)
    return torch.einsum("ntij,nj->nti", rot, graph.rest) + positions[graph.node_graph]


@dataclass
class Batch:
    history: torch.Tensor  # (N, 3, 3) float64 input positions at t-2, t-1, t
    target: torch.Tensor   # (N, 3) float64 position at t+1 (noise-corrected)
    graph: GraphBatch
    # (N, U - 1, 3) float64 positions at t+2 .. t+U for unrolled training (noise-corrected as target)
    future: torch.Tensor | None = None

    def to(self, device) -> "Batch":
        future = None if self.future is None else self.future.to(device)
        return Batch(self.history.to(device), self.target.to(device), self.graph.to(device), future)

    @property
    def targets(self) -> torch.Tensor:
        """(N, U, 3): the positions at t+1 .. t+U."""
        if self.future is None:
            return self.target[:, None]
        return torch.cat([self.target[:, None], self.future], dim=1)


class ObjectTracks:
    """All tracks of a list of scenes, with their training windows."""

    def __init__(self, scenes: list[Scene], library: MeshLibrary, name: str = "scenes", unroll: int = 1):
        if unroll < 1:
            raise ValueError(f"unroll must be >= 1, got {unroll}")
        self.unroll = unroll
        self.window = HISTORY + unroll  # frames a training window spans: inputs and the targets
        positions, quaternions, lengths, scene_of = [], [], [], []
        shapes, scale, friction, restitution = [], [], [], []
        for i, sc in enumerate(scenes):
            for n in range(sc.num_objects):
                positions.append(sc.positions[:, n])
                quaternions.append(sc.quaternions[:, n])
                lengths.append(sc.num_frames)
                scene_of.append(i)
            shapes += list(sc.shape)
            scale.append(sc.scale)
            friction.append(sc.friction)
            restitution.append(sc.restitution)
        if not lengths:
            raise DataError(f"{name}: no scenes")
        # checked on all tracks at once, scene by scene only to name the first bad one: a check a
        # scene cost ~1% of rolling out 400 MOVi-A scenes
        positions, quaternions = np.concatenate(positions), np.concatenate(quaternions)
        if not (np.isfinite(positions).all() and np.isfinite(quaternions).all()
                and (np.linalg.norm(quaternions, axis=-1) > 0).all()):
            for i, sc in enumerate(scenes):
                if not (np.isfinite(sc.positions).all() and np.isfinite(sc.quaternions).all()
                        and (np.linalg.norm(sc.quaternions, axis=-1) > 0).all()):
                    raise DataError(f"{name}: scene {i} has non-finite positions or invalid quaternions")
        try:
            self.shape_ids = library.shape_ids(shapes)
        except ValueError as e:
            raise DataError(f"{name}: {e}") from None
        self.library = library
        self.positions = torch.from_numpy(positions)      # (F, 3) all frames of all tracks
        self.quaternions = torch.from_numpy(quaternions)  # (F, 4)
        self.length = torch.tensor(lengths)
        self.track_scene = torch.tensor(scene_of)
        self.start = torch.cumsum(self.length, 0) - self.length
        self.scale = torch.from_numpy(np.concatenate(scale))
        self.friction = torch.from_numpy(np.concatenate(friction))
        self.restitution = torch.from_numpy(np.concatenate(restitution))
        # scenes: their tracks are consecutive; windows are per scene (all its objects together)
        self.scene_num_tracks = torch.bincount(self.track_scene, minlength=len(scenes))
        self.scene_first_track = torch.cumsum(self.scene_num_tracks, 0) - self.scene_num_tracks
        scene_length = torch.tensor([sc.num_frames for sc in scenes], dtype=torch.int64)
        per_scene = torch.where(self.scene_num_tracks > 0, scene_length - self.window + 1, 0).clamp(min=0)
        self.window_scene = torch.repeat_interleave(torch.arange(len(scenes)), per_scene)
        offset = torch.cumsum(per_scene, 0) - per_scene
        self.window_first = torch.arange(int(per_scene.sum())) - offset[self.window_scene]
        # the first track of each window's scene (its only track in one-object scenes)
        self.window_track = self.scene_first_track[self.window_scene]
        self.max_objects = int(self.scene_num_tracks.max())
        if self.num_windows == 0:
            raise DataError(f"{name}: no scene has the {self.window} frames a training window needs")
        self.contact = None  # (num_windows,) bool once mark_contacts ran

    @property
    def num_tracks(self) -> int:
        return len(self.length)

    @property
    def num_scenes(self) -> int:
        return int(self.track_scene.max()) + 1

    @property
    def num_windows(self) -> int:
        return len(self.window_track)

    def graph(self, tracks: torch.Tensor, graph_scene: torch.Tensor | None = None) -> GraphBatch:
        """Packed graphs of tracks (B,); graph_scene (B,) groups them into scenes of the batch
        (default: the tracks' scenes, so tracks of one scene interact)."""
        if graph_scene is None:
            graph_scene = self.track_scene[tracks]
        return self.library.pack(self.shape_ids[tracks], self.scale[tracks], self.friction[tracks],
                                 self.restitution[tracks], graph_scene)

    def window_tracks(self, windows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Tracks of the given windows' scenes (all objects) and the window (index into windows) of each."""
        scene = self.window_scene[windows]
        which, k = ragged_arange(self.scene_num_tracks[scene])
        return self.scene_first_track[scene][which] + k, which

    def poses(self, tracks: torch.Tensor, first: torch.Tensor, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Centre positions (B, frames, 3) and rotation matrices (B, frames, 3, 3) from `first` on."""
        idx = (self.start[tracks] + first)[:, None] + torch.arange(frames)
        return self.positions[idx], torch.from_numpy(quat_to_matrix(self.quaternions[idx].numpy()))

    def batch(self, windows: torch.Tensor, rng: np.random.Generator | None = None, rotate: bool = False,
              noise_std: float = 0.0, vertex_noise: float = 0.0, track_noise: float = 0.0,
              mirror: bool = False, body_symmetry: bool = False) -> Batch:
        """The graphs of the given windows (B,), packed; augmentation and noise need `rng`.

        Every object of a window's scene is in the batch (one graph each, grouped by window)."""
        tracks, window_of = self.window_tracks(windows)
        pos, rot = self.poses(tracks, self.window_first[windows][window_of], self.window)
        if track_noise > 0:
            step = (pos[:, 1:] - pos[:, :-1]).norm(dim=-1)                  # (B, window - 1)
            displacement = torch.cat([step[:, :1], step], dim=1)            # (B, window)
            pos = pos + torch.from_numpy(rng.normal(0.0, 1.0, pos.shape)) * (track_noise * displacement)[..., None]
        if rotate:
            rz = rotation_z(torch.from_numpy(rng.uniform(-np.pi, np.pi, len(windows))))[window_of]
            rot = rz[:, None] @ rot
            pos = (rz[:, None] @ pos[..., None])[..., 0]
        graph = self.graph(tracks, window_of)
        if body_symmetry:
            sym = self.library.random_symmetries(self.shape_ids[tracks], rng)      # (B, 3, 3)
            graph = replace(graph, rest=torch.einsum("nij,nj->ni", sym[graph.node_graph], graph.rest))
            rot = rot @ sym.transpose(1, 2)[:, None]
        if mirror:
            from gns.symmetry import mapped_symmetries
            flip = torch.from_numpy(rng.random(len(windows)) < 0.5)[window_of]     # (B,) per window
            m = torch.ones(len(tracks), 3, dtype=torch.float64)
            m[flip, 0] = -1.0
            pos = pos * m[:, None]
            rot = rot * m[:, None, :, None] * m[:, None, None, :]
            graph = replace(graph, rest=graph.rest * m[graph.node_graph],
                            symmetries=mapped_symmetries(graph, torch.diag_embed(m)))
        x = vertices_from_poses(graph, pos, rot)                  # (N, window, 3)
        if vertex_noise > 0:
            size = graph_sizes(graph)[graph.node_graph]           # (N,)
            offset = torch.from_numpy(rng.normal(0.0, 1.0, (graph.num_nodes, 3))) * (vertex_noise * size)[:, None]
            x = x + torch.einsum("ntij,nj->nti", rot[graph.node_graph], offset)
        history, target, future = x[:, :HISTORY], x[:, HISTORY], x[:, HISTORY + 1:]
        if noise_std > 0:
            step_std = noise_std / np.sqrt(HISTORY - 1)
            velocity_noise = rng.normal(0.0, step_std, (graph.num_nodes, HISTORY - 1, 3))
            position_noise = torch.from_numpy(np.concatenate(
                [np.zeros((graph.num_nodes, 1, 3)), np.cumsum(velocity_noise, axis=1)], axis=1))
            history = history + position_noise
            target = target + position_noise[:, -1]
            future = future + position_noise[:, -1:]
        return Batch(history, target, graph, future if self.unroll > 1 else None)

    def mark_contacts(self, gravity_step: torch.Tensor, threshold: float) -> float:
        """Flag the windows in which some object is in contact; returns the flagged share.

        A window is in contact when, at one of its target frames, some object's centre
        acceleration (second difference of the true centres) differs from free fall's
        gravity_step = g dt^2 (3,) by more than threshold x |g| dt^2. Resting, sliding,
        bouncing and object-object pushes all do; free flight does not, whatever the spin.
        Tracking noise of real data adds a few tens of % of |g| dt^2 to free flight, so
        threshold ~0.5 still separates the two.
        """
        hit = in_contact(self.positions, gravity_step, threshold)  # (F,) all frames of all tracks; valid inside tracks only
        return self._flag_windows(hit)

    def mark_objects_near(self) -> float:
        """Flag the windows in which two objects of a scene are near each other: at one of the
        frames mark_contacts looks at, their bounding spheres (radius: the farthest vertex of the
        scaled mesh) touch. Returns the flagged share (0 in scenes of one object)."""
        radius = self.library.radius[self.shape_ids] * self.scale
        hit = torch.zeros(len(self.positions), dtype=torch.bool)
        for scene in torch.nonzero(self.scene_num_tracks > 1)[:, 0].tolist():
            first, n = int(self.scene_first_track[scene]), int(self.scene_num_tracks[scene])
            start, length = int(self.start[first]), int(self.length[first])
            x = self.positions[start:start + n * length].view(n, length, 3)
            gap = (x[:, None] - x[None]).norm(dim=-1) - (radius[first:first + n, None] + radius[None, first:first + n])[..., None]
            gap[torch.arange(n), torch.arange(n)] = float("inf")
            hit[start:start + n * length] = (gap < 0).any(dim=1).reshape(-1)
        return self._flag_windows(hit)

    def _flag_windows(self, hit: torch.Tensor) -> float:
        """Windows flagged where some track's frame is flagged in hit (F,); returns the flagged share."""
        # a window of scene s, first frame f: its targets are frames f+HISTORY .. f+window-1;
        # the second difference at frame k needs k-1 .. k+1, so look at k = f+HISTORY-1 .. f+window-2
        tracks, window_of = self.window_tracks(torch.arange(self.num_windows))
        first = self.start[tracks] + self.window_first[window_of]
        frames = first[:, None] + torch.arange(HISTORY - 1, self.window - 1)
        per_track = hit[frames].any(dim=1)
        self.contact = torch.zeros(self.num_windows, dtype=torch.float64).index_add_(0, window_of, per_track.double()) > 0
        return float(self.contact.double().mean())

    def sample(self, rng: np.random.Generator, batch_size: int, rotate: bool, noise_std: float,
               vertex_noise: float = 0.0, track_noise: float = 0.0, contact_fraction: float = 0.0,
               mirror: bool = False, body_symmetry: bool = False) -> Batch:
        """A random batch; with contact_fraction > 0 (after mark_contacts) that share of its windows,
        rounded at random, from the windows in contact, the rest from all windows."""
        if contact_fraction > 0 and self.contact is not None and self.contact.any():
            contact = torch.nonzero(self.contact)[:, 0]
            n_contact = int(rng.binomial(batch_size, contact_fraction))
            windows = torch.cat([contact[torch.from_numpy(rng.integers(0, len(contact), n_contact))],
                                 torch.from_numpy(rng.integers(0, self.num_windows, batch_size - n_contact))])
        else:
            windows = torch.from_numpy(rng.integers(0, self.num_windows, batch_size))
        return self.batch(windows, rng, rotate, noise_std, vertex_noise, track_noise, mirror, body_symmetry)

    def track_vertices(self, tracks: torch.Tensor, frames: int) -> tuple[GraphBatch, torch.Tensor, torch.Tensor]:
        """For rollouts: graph, vertices (N, frames, 3) and centres (B, frames, 3) from frame 0."""
        pos, rot = self.poses(tracks, torch.zeros_like(tracks), frames)
        graph = self.graph(tracks)
        return graph, vertices_from_poses(graph, pos, rot), pos


def in_contact(centres: torch.Tensor, gravity_step: torch.Tensor, threshold: float) -> torch.Tensor:
    """centres (..., F, 3) -> (..., F) bool: the centre's acceleration at each frame (second
    difference over the frames before and after) differs from free fall's gravity_step = g dt^2
    by more than threshold x |g| dt^2. The first and last frame have no second difference: False."""
    g = gravity_step.to(torch.float64)
    hit = torch.zeros(centres.shape[:-1], dtype=torch.bool)
    accel = centres[..., 2:, :] - 2 * centres[..., 1:-1, :] + centres[..., :-2, :] - g
    # compared in float32, as the training's contact windows always were
    hit[..., 1:-1] = accel.norm(dim=-1).float() > threshold * float(g.norm())
    return hit


def _range(values: list[np.ndarray]) -> tuple[float, float]:
    flat = np.concatenate([np.ravel(v) for v in values])
    return float(flat.min()), float(flat.max())


def feature_spec(dataset: Dataset, scenes: list[Scene]) -> ModelSpec:
    """What a model trained on these scenes was shown: physics constants and value ranges.

    Ranges are (min, max). Speeds are finite differences between frames, as the model sees
    them: centre speed in scene units per second, rotation speed in radians per second.
    """
    rate = dataset.frame_rate
    try:
        floor = None if dataset.floor is None else Floor.from_dict(dataset.floor)
    except SpecError as e:
        raise DataError(f"the data's metadata: {e}") from None
    return ModelSpec(
        frame_rate=dataset.frame_rate,
        gravity=tuple(dataset.gravity.tolist()),
        floor=floor,
        materials_vary=dataset.materials_vary,
        # objects interact (collision edges) only if some scene holds more than one
        collision_edges=max(sc.num_objects for sc in scenes) > 1,
        shapes=tuple(sorted({s for sc in scenes for s in sc.shape})),
        ranges={
            "speed": _range([np.linalg.norm(np.diff(sc.positions, axis=0), axis=-1) * rate for sc in scenes]),
            "angular_speed": _range([rotation_angle(sc.quaternions[1:], sc.quaternions[:-1]) * rate
                                     for sc in scenes]),
            "height": _range([sc.positions[..., 2] for sc in scenes]),
            "scale": _range([sc.scale for sc in scenes]),
            "friction": _range([sc.friction for sc in scenes]),
            "restitution": _range([sc.restitution for sc in scenes]),
        },
    )


def load_data(data_dir: str | Path, cfg: Config) -> tuple[ModelSpec, ObjectTracks, ObjectTracks | None]:
    """Feature spec, train tracks and (if validating and present) valid tracks of a dataset."""
    dataset = Dataset(data_dir, stride=cfg.features.frame_stride)
    limit = cfg.train.scenes or None
    scenes = dataset.load("train", limit)
    if limit is not None and len(scenes) < limit:
        raise ConfigError(f"train.scenes={limit}, but {data_dir} holds {len(scenes)} train scenes")
    k = cfg.features.frame_stride
    if k > 1 and cfg.train.all_phases:
        # read at stride k from frame 0 only, a scene gives 1/k of its windows; starting at each
        # of frames 0 .. k-1 gives them all (as many windows as at stride 1)
        full = Dataset(data_dir).load("train", limit)
        scenes = [sc.every(k, phase) for sc in full for phase in range(k) if sc.num_frames > phase]
    try:
        library = MeshLibrary(dataset.meshes, **graph_settings(cfg.features))
    except ValueError as e:
        raise DataError(f"{data_dir}: {e}") from None
    tracks = ObjectTracks(scenes, library, "train split", unroll=cfg.train.unroll_steps)
    if cfg.train.contact_fraction > 0 and cfg.train.contact_kind == "objects":
        tracks.mark_objects_near()
    elif cfg.train.contact_fraction > 0:
        tracks.mark_contacts(torch.as_tensor(dataset.gravity, dtype=torch.float64) / dataset.frame_rate ** 2,
                             cfg.train.contact_threshold)
    valid = None
    if cfg.valid.every > 0 and "valid" in dataset.splits:
        valid = ObjectTracks(dataset.load("valid"), library, "valid split")
    # the meshes travel with the model: gns.load rolls out without the dataset
    spec = replace(feature_spec(dataset, scenes),
                   meshes={name: (torch.as_tensor(np.asarray(v, np.float64)), torch.as_tensor(np.asarray(f, np.int64)))
                           for name, (v, f) in dataset.meshes.items()})
    return spec, tracks, valid
