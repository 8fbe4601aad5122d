"""What a trained checkpoint may carry on as: the start of a fine-tuning run (train.init_from),
or a resumed run, on data whose feature spec may differ in what fine-tuning allows.

A fine-tune may change FINE_TUNE_FREE (the weights keep their shapes), untie a repeated processor
(model.message_passing_steps a multiple of the checkpoint's: block i starts as the trained block
i mod L, so with L x K kept the start computes exactly what the checkpoint did), and grow
collision edges onto a model trained on single objects (`_grown`: the new edge set's encoder and
functions start fresh and its messages enter each node update through weights that start at
zero, so the start computes exactly what the single-object model did, collisions or not, and
training adds only what contacts between objects need); everything else of the architecture
must match.
"""
from __future__ import annotations

import warnings
from dataclasses import replace

import torch

from gns.checkpoint import CONTACT, CheckpointError, checkpoint_of, read_checkpoint
from gns.config import ARCHITECTURE_SECTIONS, Config, ConfigError, ModelConfig, config_differences, without_removed
from gns.network import Normalizer
from gns.simulator import LearnedSimulator
from gns.spec import Floor, ModelSpec


def merge_ranges(old: ModelSpec, new: ModelSpec) -> ModelSpec:
    """The spec of training on old data then new data: value ranges and shapes united."""
    ranges = {k: (min(old.ranges[k][0], v[0]), max(old.ranges[k][1], v[1])) for k, v in new.ranges.items()}
    return replace(new, ranges=ranges, shapes=tuple(sorted(set(old.shapes) | set(new.shapes))),
                   meshes={**(old.meshes or {}), **(new.meshes or {})})


def _shown(value):
    """A spec value as checkpoints hold it (lists, dicts), for messages."""
    return value.to_dict() if isinstance(value, Floor) else list(value) if isinstance(value, tuple) else value


def init_from(sim: LearnedSimulator, source: str, cfg: Config, spec: ModelSpec) -> ModelSpec:
    """Load another run's weights and normalisers into a new run's simulator (fine-tuning); returns
    the spec with the two datasets' ranges united. The loaded normalisers have spent their
    accumulation budget, so they stay as the weights were trained with."""
    path = checkpoint_of(source)   # a run folder, a .pt file or a shipped model's name
    init = read_checkpoint(path)
    try:
        without_removed(init["config"], f"{path} (train.init_from)")
    except ConfigError as e:
        raise CheckpointError(str(e)) from None
    trained = ModelSpec.from_dict(init["spec"])
    problems = [incompatibility(init["config"], trained, cfg, spec, fine_tune=True)]
    for key in ("frame_rate", "gravity"):
        if getattr(trained, key) != getattr(spec, key):
            problems.append(f"{key} is {_shown(getattr(trained, key))} there, {_shown(getattr(spec, key))} in this data")
    problem = "; ".join(p for p in problems if p)
    if problem:
        raise CheckpointError(f"cannot start from {path} (train.init_from): {problem}")
    if CONTACT in init:
        warnings.warn(f"{path} (train.init_from) carries a contact network: training starts from the model's own "
                      "network, without it", stacklevel=2)
    state = _untied(init["model"], sim)
    if _grows(trained, spec):
        state = _grown(state, sim)
    sim.load_state_dict(state)
    return merge_ranges(trained, spec)


def _grows(trained: ModelSpec, spec: ModelSpec) -> bool:
    """Whether a fine-tune grows collision edges: data of several objects a scene, a checkpoint without them."""
    return spec.collision_edges and not trained.collision_edges


def _grown(state: dict, sim: LearnedSimulator) -> dict:
    """A single-object model's `state` for `sim`, which has collision edges: the collision edge
    set's encoder, edge functions and normalisers as `sim` initialised them, and each node
    update's first layer widened with zero columns for the summed collision messages (its input
    is [node, mesh messages, collision messages], so the trained columns come first)."""
    out = dict(state)
    for key, fresh in sim.state_dict().items():
        old = state.get(key)
        if old is None:
            out[key] = fresh                       # a collision part: as initialised
        elif old.shape != fresh.shape:
            if not (".node_mlp.0.weight" in key and old.shape[0] == fresh.shape[0] and old.shape[1] < fresh.shape[1]):
                raise CheckpointError(f"cannot grow collision edges onto the checkpoint: {key} is "
                                      f"{tuple(old.shape)} there, {tuple(fresh.shape)} here")
            widened = torch.zeros_like(fresh)
            widened[:, :old.shape[1]] = old
            out[key] = widened
    return out


def _is_collision_part(name: str) -> bool:
    return name.startswith(("network.collision_encoder.", "collision_normalizers.")) or ".collision." in name


def train_collisions_only(sim: LearnedSimulator) -> None:
    """Only the parts `_grown` added train (train.collisions_only): every other weight stops
    taking gradients, and each node update's first layer keeps the trained columns of [node,
    mesh messages] by a gradient hook that zeroes them (Adam then never moves them: its moments
    stay 0); the trained normalisers stop accumulating. Found by name, so a resumed run freezes
    the same weights."""
    if not sim.network.collisions:
        raise CheckpointError("train.collisions_only needs collision edges (data of several objects a scene)")
    for name, module in sim.named_modules():
        if isinstance(module, Normalizer) and not _is_collision_part(name + "."):
            module.max_accumulations = int(module.accumulations)
    kept = 2 * sim.network.blocks[0].node_mlp[0].weight.shape[1] // 3   # [node, mesh, collision] latents
    for name, param in sim.named_parameters():
        if _is_collision_part(name):
            continue
        if name.endswith(".node_mlp.0.weight"):
            param.register_hook(lambda grad, kept=kept: torch.cat([torch.zeros_like(grad[:, :kept]), grad[:, kept:]], 1))
        else:
            param.requires_grad_(False)


def _untied(state: dict, sim: LearnedSimulator) -> dict:
    """`state` for `sim`'s L processor blocks where the checkpoint has L / m of them: block i
    starts as the trained block i mod (L / m). A checkpoint that applied its blocks K times thus
    becomes K / m applications of m copies, the same function at the same cost, whose copies
    then train apart (more parameters, no more work a step)."""
    trained = {int(k.split(".")[2]) for k in state if k.startswith("network.blocks.")}
    if not trained or len(sim.network.blocks) == len(trained):
        return dict(state)
    out = {k: v for k, v in state.items() if not k.startswith("network.blocks.")}
    for key, value in state.items():
        if key.startswith("network.blocks."):
            index, rest = key.split(".", 3)[2:]
            for copy in range(int(index), len(sim.network.blocks), len(trained)):
                out[f"network.blocks.{copy}.{rest}"] = value.clone()
    return out


# keys a fine-tuning run (train.init_from) may change: the weights keep their shapes
FINE_TUNE_FREE = ("features.centre_node", "model.processor_repeats", "features.canonical_heading",
                  "features.surface_edges", "features.lowest_vertices", "features.highest_vertices",
                  "features.collision_radius", "features.collision_mode", "features.collision_velocity")


def incompatibility(config: dict, trained: ModelSpec, cfg: Config, spec: ModelSpec,
                     fine_tune: bool = False) -> str | None:
    """How a checkpoint (its config and spec) cannot carry on as the model of cfg on data of spec.
    fine_tune: as the start of a new run, which may change FINE_TUNE_FREE (a resumed run may not)."""
    diffs = config_differences(config, cfg, ARCHITECTURE_SECTIONS,
                               ignore=(*FINE_TUNE_FREE, "model.message_passing_steps") if fine_tune else ())
    if fine_tune:
        steps = config.get("model", {}).get("message_passing_steps", ModelConfig().message_passing_steps)
        if cfg.model.message_passing_steps % steps:
            diffs.append(f"model.message_passing_steps is {steps} in the checkpoint, {cfg.model.message_passing_steps} "
                         f"now: a fine-tune may only untie its blocks into a multiple of them")
    grows = fine_tune and _grows(trained, spec)
    for key in ("node_features", "edge_features", "collision_features"):
        if key == "collision_features" and grows:
            continue                               # collision edges grown onto a single-object model
        theirs, mine = tuple(getattr(trained, key) or ()), tuple(getattr(spec, key))
        if theirs != mine:
            diffs.append(f"{key} are {list(getattr(trained, key) or ())} in the checkpoint, "
                         f"{list(getattr(spec, key))} with this data")
    old_floor, new_floor = trained.floor, spec.floor
    if (old_floor is None) != (new_floor is None) or (old_floor and old_floor.z != new_floor.z):
        diffs.append(f"floor is {_shown(old_floor)} in the checkpoint, {_shown(new_floor)} in this data")
    return "; ".join(diffs) or None
