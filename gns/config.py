"""Training configuration: dataclasses with defaults, TOML presets and `--set key=value` overrides.

Every key a user can set is a dataclass field, so an unknown key is an error that names the key
and the nearest known one. The defaults are the paper's model (L = 10, K = 3, latent 128); the
presets in configs/ override what they need.
"""
from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, field
from pathlib import Path


# one error class, one value parser and one typing rule for datagen's and gns's configs
from plumbing import ConfigError, load_toml, parse_value, typed_value


@dataclass
class ModelConfig:
    latent_size: int = 128
    hidden_size: int = 128
    hidden_layers: int = 2             # hidden layers of every MLP
    message_passing_steps: int = 10    # L: blocks with unshared weights
    processor_repeats: int = 3         # K: the L blocks are applied K times


@dataclass
class FeatureConfig:
    encoding: str = "relative"         # "relative" (paper) or "absolute" (the unstable ablation)
    velocity: bool = True              # 2 finite-difference velocities per node
    floor_distance: bool = True        # used only when the dataset has a floor
    floor_clip: float = 0.5            # floor distance clipped to [0, floor_clip], scene units
    # clip to [-floor_clip, floor_clip]: a vertex below the floor shows how deep (a rollout's
    # penetration), instead of reading as touching
    floor_signed: bool = False
    material: bool = True              # friction, restitution; used only when materials vary
    rest_position: bool = True         # body-frame rest position of each vertex (node feature)
    rest_edges: bool = True            # d^U and |d^U| on edges (relative encoding only)
    # no input depends on the body frame: the rest position and the rest edge vector (body-frame
    # vectors) give way to their lengths, |x^U| on nodes and |d^U| on edges. With spokes only
    # (centre_node, surface_edges=false) the network is then exactly invariant to which of a
    # mesh's equivalent body frames describes an object (a cube's 24), for any weights
    body_frame_free: bool = False
    normalizer_steps: int = 1000       # training steps during which normalisers accumulate
    collision_radius: float = 0.15     # collision edges between objects closer than this, scene units
    # collision edges vertex-vertex or vertex-to-surface (gns.contacts), or face-face (gns.face_contacts)
    collision_mode: str = "vertex"
    # collision edges also carry v_r - v_s, the two ends' velocities over the last frame (in the
    # receiving object's heading): with an object turned to its own heading, the sender's latent
    # holds its velocity in another frame, so the edge function could not form it
    collision_velocity: bool = False
    frame_stride: int = 1              # train on every k-th recorded frame: the time step is k / frame_rate
    # a node at each object's centre of mass joined to all its vertices (gns.graph.centre_spokes):
    # every vertex two message-passing steps from every other, whatever the mesh
    centre_node: bool = False
    # with centre_node: false leaves each object's graph only its spokes, no surface edges. The
    # graph stays 2 steps across, with 2n edges instead of 2n + ~6n: a cheaper network call for
    # the fast end of the speed trade (experiments/log.md)
    surface_edges: bool = True
    # the network sees each scene turned about z so that its mean horizontal velocity points
    # along +x, and its answer is turned back: exactly equivariant to turns about z at one network
    # call (rotation augmentation only teaches it approximately; averaging turned images, as
    # --symmetrize c2 does, measured 1.6 points better at twice the cost, experiments/log.md;
    # fine-tuned with it, 1.25 points and 2.3 degrees better at one call on MOVi-A, no gain on real
    # cubes)
    canonical_heading: bool = False
    # > 0: at every step the network sees only each object's k vertices nearest the floor and
    # its centre node (needs centre_node), the rest of the object following the pose that shape
    # matching fits to those: a contact's geometry at the full mesh's resolution, the far side of
    # the object (which only tells the pose, which the centre and k vertices tell too) left out,
    # so a network call costs about (k + 1) / (n + 1) of the full mesh's. 0 = every vertex
    lowest_vertices: int = 0
    # with lowest_vertices: the network also sees each object's this many highest vertices, so
    # that the pose fitted to the nodes it sees rests on points far apart (a fit to a small
    # patch turns the errors of a few vertices into a large turn)
    highest_vertices: int = 0


@dataclass
class AugmentConfig:
    rotate: bool = True                # rotate input and target about z by U[-pi, pi]
    noise_std: float = 0.003           # random-walk noise, std on the last input frame, scene units
    vertex_noise: float = 0.0          # shape noise (paper Fig. 7a): std of one fixed offset per vertex, x size
    track_noise: float = 0.0           # tracking noise (Fig. 7b): std of per-frame centre noise, x its displacement
    mirror: bool = False               # mirror half the windows in x, body frame included (gns.data)
    body_symmetry: bool = False        # describe each object in a random one of its mesh's symmetric body frames


@dataclass
class TrainConfig:
    steps: int = 1_000_000
    batch_size: int = 8                # windows per step (one graph per object of the window's scene)
    lr_init: float = 1e-4
    lr_final: float = 1e-6
    lr_decay_steps: int = 5_000_000    # lr - lr_final shrinks 10x every lr_decay_steps
    grad_clip: float = 1.0             # max global gradient norm; 0 disables clipping
    seed: int = 0
    threads: int = 0                   # torch threads; 0 = all cores
    device: str = "cpu"                # with torchrun on CUDA each process takes cuda:LOCAL_RANK
    autocast: str = "none"             # "bf16": the network (only) runs under bfloat16 autocast; "auto": bf16 where it measures faster
    compile: bool = False              # the network through torch.compile (with bf16: 2.1x steps/s, bench_train.py)
    log_every: int = 100
    checkpoint_every: int = 1000
    keep_checkpoints: int = 3          # numbered checkpoints kept besides latest.pt; 0 keeps all
    # This share of each batch is drawn from the windows in contact (some centre acceleration
    # differs from free fall by more than contact_threshold x |g| dt^2), the rest from all
    # windows, contact ones included; 0 samples all windows alike.
    contact_fraction: float = 0.0
    contact_threshold: float = 0.5
    # "objects": the windows drawn by contact_fraction are instead those in which two objects of a
    # scene come near each other (their bounding spheres touch), whatever the floor does
    contact_kind: str = "any"
    # Steps of pushforward training: the model predicts unroll_steps frames from 3 true ones, each
    # step on its own (shape-matched) earlier predictions, detached; the loss averages all steps.
    unroll_steps: int = 1
    # With features.frame_stride k > 1, train on windows starting at every frame (k phases of each
    # scene), not only at multiples of k: k times the windows from the same data.
    all_phases: bool = False
    # > 0: train on the dataset's first this many train scenes only (0: all of them). Datagen keys
    # each scene by (seed, split, index), so the first N of a larger dataset are the N-scene dataset
    # of the same seed: a chain can start on a few scenes and go on to more, and a training-set size
    # curve needs one dataset
    scenes: int = 0
    # > 0 adds this weight times a loss on what a rollout keeps of a prediction: the shape-matched
    # next vertices (the rest mesh fitted to the predicted ones, differentiably) against the
    # shape-matched true ones, per node and axis in the target normaliser's units. The per-node
    # loss also spends the network on the non-rigid part of its answer, which shape matching
    # throws away (gns.simulator.LearnedSimulator.loss)
    rigid_loss: float = 0.0
    tensorboard: bool = False          # also write TensorBoard event files to RUN/tb (the tensorboard extra)
    # Start a new run from another run's weights and normalisers (a run folder or .pt): fine-tuning,
    # e.g. on real tosses after training on an engine's. Same architecture, features, frame rate.
    init_from: str = ""
    # With init_from growing collision edges onto a single-object model: only the collision parts
    # train (their encoder, edge functions, normalisers and the columns through which their messages
    # enter each node update); the rest stays the checkpoint's, so every object that has no collision
    # edge (all of a single-object scene) rolls out exactly as the single-object model did
    collisions_only: bool = False
    # In (0, 1): the run saves an exponential moving average of its weights with this decay (about
    # the last 1 / (1 - decay) steps) as the model to use, and trains on from its own (gns.weight_average)
    ema_decay: float = 0.0


@dataclass
class ValidConfig:
    every: int = 1000                  # steps between validations; 0 disables validation
    windows: int = 256                 # valid windows for the one-step loss
    rollout_scenes: int = 4
    rollout_steps: int = 10


@dataclass
class Config:
    model: ModelConfig = field(default_factory=ModelConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    valid: ValidConfig = field(default_factory=ValidConfig)


# Keys of rigid-gns 0.1 that lost to others (measured no better, set by no shipped model), with
# the value every checkpoint trained without them holds: such a checkpoint loads as if the key had
# never been. One that set a key to anything else was trained with code that no longer exists.
REMOVED_IN = "rigid-gns 0.2"
REMOVED = {
    "model.inertial_prior": "linear",
    "features.velocity_direction": 0.0, "features.mesh_vertices": 0, "features.mesh_support_gap": 0.0,
    "features.surface_edge_shapes": "", "features.impact_time": False, "features.edge_velocity": False,
    "features.canonical_mirror": False, "features.floor_support": False, "features.canonical_body_frame": False,
    "augment.spin_noise": 0.0,
    "train.hard_fraction": 0.0, "train.hard_every": 2500, "train.loss": "mse", "train.huber_delta": 1.0,
    "train.size_weight": 0.0, "train.teacher": "", "train.teacher_weight": 1.0, "train.teacher_symmetrize": "",
}


def without_removed(saved: dict, where: str = "this checkpoint") -> dict:
    """A checkpoint's config dict without the REMOVED keys it holds at their old values;
    ConfigError (one line) if it set one to anything else."""
    out = {}
    for section, values in saved.items():
        if not isinstance(values, dict):
            out[section] = values
            continue
        out[section] = {}
        for key, value in values.items():
            name = f"{section}.{key}"
            if name not in REMOVED:
                out[section][key] = value
            elif value != REMOVED[name]:
                raise ConfigError(f"{where} uses {name}={value!r}, removed in {REMOVED_IN}")
    return out


# Changing any key in these sections changes the network or its inputs, so a checkpoint trained
# with other values cannot be resumed with them.
ARCHITECTURE_SECTIONS = ("model", "features")


def config_to_dict(cfg: Config) -> dict:
    return dataclasses.asdict(cfg)


def known_keys() -> list[str]:
    return [f"{s.name}.{k.name}" for s in dataclasses.fields(Config)
            for k in dataclasses.fields(s.default_factory)]


def _unknown_key(key: str, where: str) -> ConfigError:
    candidates = known_keys() + [f.name for f in dataclasses.fields(Config)]
    close = difflib.get_close_matches(key, candidates, n=1, cutoff=0.5)
    hint = (f"; did you mean '{close[0]}'?" if close
            else f"; sections are {', '.join(f.name for f in dataclasses.fields(Config))}")
    return ConfigError(f"unknown config key '{key}' {where}{hint}")


def apply_dict(cfg: Config, data: dict, where: str) -> Config:
    """Set every key of a nested dict {section: {key: value}} on cfg, strictly."""
    sections = {f.name for f in dataclasses.fields(cfg)}
    for section, values in data.items():
        if section not in sections:
            first = next(iter(values), None) if isinstance(values, dict) else None
            raise _unknown_key(section if first is None else f"{section}.{first}", where)
        if not isinstance(values, dict):
            raise ConfigError(f"config key '{section}' {where} must be a table of keys")
        sub = getattr(cfg, section)
        for key, value in values.items():
            name = f"{section}.{key}"
            if key not in {f.name for f in dataclasses.fields(sub)}:
                raise _unknown_key(name, where)
            setattr(sub, key, typed_value(name, value, getattr(sub, key), where))
    return cfg


def parse_override(text: str) -> dict:
    """'section.key=value' -> {section: {key: value}}; the value read as datagen's --set reads it."""
    if "=" not in text:
        raise ConfigError(f"override '{text}' is not of the form section.key=value")
    key, raw = (s.strip() for s in text.split("=", 1))
    if key.count(".") != 1:
        raise _unknown_key(key, "in --set")
    value = parse_value(raw)
    section, name = key.split(".")
    return {section: {name: value}}


def build_config(base: dict | None = None, path: str | Path | None = None,
                 overrides: list[str] = ()) -> Config:
    """Defaults, then `base` (a saved config dict), then the TOML file, then each override."""
    cfg = Config()
    if base is not None:
        apply_dict(cfg, without_removed(base), "in the checkpoint")
    if path is not None:
        apply_dict(cfg, load_toml(path), f"in {path}")
    for text in overrides:
        apply_dict(cfg, parse_override(text), "in --set")
    validate(cfg)
    return cfg


def validate(cfg: Config) -> None:
    checks = [
        (cfg.features.encoding in ("relative", "absolute"), "features.encoding must be 'relative' or 'absolute'"),
        (cfg.model.latent_size > 0 and cfg.model.hidden_size > 0, "model sizes must be positive"),
        (cfg.model.hidden_layers >= 0, "model.hidden_layers must be >= 0"),
        (cfg.model.message_passing_steps >= 1 and cfg.model.processor_repeats >= 1,
         "model.message_passing_steps and model.processor_repeats must be >= 1"),
        (cfg.features.floor_clip > 0, "features.floor_clip must be > 0"),
        (cfg.features.collision_radius > 0, "features.collision_radius must be > 0"),
        (cfg.features.collision_mode in ("vertex", "surface", "face"),
         "features.collision_mode must be 'vertex', 'surface' or 'face'"),
        (cfg.features.frame_stride >= 1, "features.frame_stride must be >= 1"),
        (cfg.features.lowest_vertices == 0 or cfg.features.lowest_vertices >= 3,
         "features.lowest_vertices must be 0 (every vertex) or >= 3 (with the centre, a pose)"),
        (cfg.features.lowest_vertices == 0 or cfg.features.centre_node,
         "features.lowest_vertices needs features.centre_node=true (each kept vertex's way to the others)"),
        (cfg.features.highest_vertices >= 0, "features.highest_vertices must be >= 0"),
        (cfg.features.highest_vertices == 0 or cfg.features.lowest_vertices > 0,
         "features.highest_vertices needs features.lowest_vertices > 0"),
        (cfg.features.surface_edges or cfg.features.centre_node,
         "features.surface_edges=false needs features.centre_node=true (the spokes are then the only edges)"),
        (cfg.augment.noise_std >= 0, "augment.noise_std must be >= 0"),
        (cfg.augment.vertex_noise >= 0, "augment.vertex_noise must be >= 0"),
        (cfg.augment.track_noise >= 0, "augment.track_noise must be >= 0"),
        (cfg.train.batch_size >= 1, "train.batch_size must be >= 1"),
        (cfg.train.autocast in ("none", "bf16", "auto"), "train.autocast must be 'none', 'bf16' or 'auto'"),
        (cfg.train.steps >= 0, "train.steps must be >= 0"),
        (cfg.train.lr_init > 0 and cfg.train.lr_final >= 0, "learning rates must be positive"),
        (cfg.train.lr_decay_steps > 0, "train.lr_decay_steps must be > 0"),
        (0 <= cfg.train.contact_fraction <= 1, "train.contact_fraction must be in [0, 1]"),
        (cfg.train.contact_threshold > 0, "train.contact_threshold must be > 0"),
        (cfg.train.contact_kind in ("any", "objects"), "train.contact_kind must be 'any' or 'objects'"),
        (cfg.train.unroll_steps >= 1, "train.unroll_steps must be >= 1"),
        (cfg.train.scenes >= 0, "train.scenes must be >= 0 (0: all train scenes)"),
        (cfg.train.rigid_loss >= 0, "train.rigid_loss must be >= 0"),
        (0 <= cfg.train.ema_decay < 1, "train.ema_decay must be in [0, 1) (0: off)"),
        (not cfg.train.collisions_only or cfg.train.init_from,
         "train.collisions_only needs train.init_from (the single-object model the collision edges grow onto)"),
        (cfg.train.log_every >= 1 and cfg.train.checkpoint_every >= 1,
         "train.log_every and train.checkpoint_every must be >= 1"),
        (cfg.valid.every >= 0 and cfg.valid.rollout_steps >= 1, "valid.every must be >= 0, valid.rollout_steps >= 1"),
    ]
    for ok, message in checks:
        if not ok:
            raise ConfigError(message)


def architecture_differences(saved: dict, current: Config) -> list[str]:
    """Keys of the architecture sections whose values differ, as 'key: saved -> current'."""
    return config_differences(saved, current, ARCHITECTURE_SECTIONS)


def config_differences(saved: dict, current: Config, sections=None, ignore: tuple[str, ...] = ()) -> list[str]:
    """Keys of `sections` (default all) whose values differ between a checkpoint's config dict
    and `current`, as 'section.key is old in the checkpoint, new now'; `ignore` names
    'section.key's left out."""
    now, default = config_to_dict(current), config_to_dict(Config())
    out = []
    for section in sections or now:
        for key, value in now[section].items():
            if f"{section}.{key}" in ignore:
                continue
            # a key newer than the checkpoint had its default value then
            old = saved.get(section, {}).get(key, default[section][key])
            if old != value:
                out.append(f"{section}.{key} is {old!r} in the checkpoint, {value!r} now")
    return out
