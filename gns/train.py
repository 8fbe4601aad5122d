"""The training loop: sample windows, one Adam step on the per-node MSE, validate, checkpoint.

A run folder holds `ckpt-NNNNNN.pt` (the newest `train.keep_checkpoints`), `latest.pt`, `metrics.jsonl`
(one JSON object a line), `config.json`, `provenance.json` (library versions, code commit, the data's
path and fingerprint; also in every checkpoint) and, with `train.tensorboard`, TensorBoard event files
in `tb/`. A checkpoint alone rebuilds the model (`load_model`) and resumes training exactly: it holds
the model with its normalisers, the optimiser, the step, the RNG states, the full config and the
dataset's feature spec. The learning rate is a function of the step and the train.lr_* keys: there is
no scheduler state to save.
"""
from __future__ import annotations

import contextlib
import math
import random
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from datagen.shards import Dataset
from gns.checkpoint import CHECKPOINT_FORMAT, TRAIN_SECONDS, TRAINED, CheckpointError, build_simulator, save_checkpoint
from gns.config import Config, config_to_dict
from gns.data import Batch, ObjectTracks, load_data
from gns.network import HISTORY
from gns.geometry import shape_match_packed
from gns.run_folder import (METRICS, StopRequest, World, check_start, progress_bar, restore_rng, rng_state,
                            run_provenance, set_threads, start_run_folder, world_from_env, write_metrics)
from gns.simulator import LearnedSimulator
from gns.spec import ModelSpec

CONTACTS_COMPILE_STEPS = 500   # a compile of tens of seconds repays itself in a few hundred steps (log.md)


if TYPE_CHECKING:
    from gns.weight_average import WeightAverage


class TrainingError(Exception):
    """Training cannot go on (e.g. the loss became NaN). One line for a user."""


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM stopped a training after saving a checkpoint at the step it had reached."""


def train(data_dir: str | Path, run_dir: str | Path, cfg: Config, resume: bool = False,
          overwrite: bool = False, log: Callable[[str], None] = print) -> int:
    """Train until cfg.train.steps; returns the final step.

    Launched by torchrun with WORLD_SIZE > 1, each process trains on its share of every global batch
    of cfg.train.batch_size windows (DistributedDataParallel; see gns.processes): the same updates as
    one process with that batch, in 1/WORLD_SIZE of the network time. Only rank 0 writes and logs.

    Raises DataError, CheckpointError or TrainingError with one-line messages. Nothing in the
    run folder changes until the data, config and checkpoint have all been checked.
    """
    world = world_from_env()
    if not world.main:
        log = _quiet
    run = Path(run_dir)
    stale, device, resumed = check_start(run, cfg, world, resume, overwrite, log)
    data_spec, tracks, valid = load_data(data_dir, cfg)
    fingerprint = Dataset(data_dir).fingerprint
    rng = _seed(cfg, log)
    sim, optimizer, spec, step, average = _build_model(cfg, data_spec, resumed, rng)
    _place_model(sim, cfg, device, world, cfg.train.steps - step)
    resumed_from, ckpt = resumed if resumed else (None, {})
    finished = False
    try:
        provenance = run_provenance(data_dir, fingerprint, step, ckpt.get("provenance"))
        step = _train_loop(run, cfg, sim, optimizer, tracks, valid, spec, step, rng, device, world,
                           stale, resumed_from, provenance, log, average, float(ckpt.get(TRAIN_SECONDS, 0.0)))
        finished = True
        return step
    finally:
        # the DDP reducer must go before its process group: freed after it (when train returned),
        # its destructor hung 3 runs in ~45 (none in 80 since)
        sim.distribute(None)
        if world.size > 1:
            from gns.processes import stop
            stop(world, together=finished)


def _quiet(line: str) -> None:
    """The log of processes other than rank 0: one copy of every line is enough."""


def _seed(cfg: Config, log: Callable[[str], None]) -> np.random.Generator:
    """Threads and random state; returns the generator that draws the batches."""
    set_threads(cfg.train.threads, log)
    # the same seed in every process: all draw the same global batches and keep their share
    torch.manual_seed(cfg.train.seed)
    random.seed(cfg.train.seed)
    return np.random.default_rng(cfg.train.seed)


def adam(params, lr: float) -> torch.optim.Optimizer:
    """Adam with its fused kernel where this torch has one for the parameters' device (CPU from
    torch 2.4): 1.04-1.11x steps/s on the shipped recipes, whose many small tensors make the
    per-parameter loop a tenth of a step (experiments/log.md); the plain loop elsewhere."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(params, lr=lr)


def _build_model(cfg: Config, data_spec: ModelSpec, resumed: tuple[Path, dict] | None, rng: np.random.Generator
                 ) -> tuple[LearnedSimulator, torch.optim.Optimizer, ModelSpec, int, WeightAverage | None]:
    """The simulator and its optimiser: new, started from train.init_from's weights, or where
    the resumed checkpoint left them (weights, optimiser, step, feature ranges, random state).
    Returns (simulator, optimiser, spec, step, the weight average if train.ema_decay asks for one)."""
    sim = build_simulator(cfg, data_spec)
    spec = replace(data_spec, node_features=tuple(n for n, _ in sim.layout.node_groups),
                   edge_features=tuple(n for n, _ in sim.layout.edge_groups),
                   collision_features=tuple(n for n, _ in sim.layout.collision_groups))
    optimizer = adam(sim.parameters(), cfg.train.lr_init)
    decay = cfg.train.ema_decay
    # imported only where used: a plain training from scratch loads neither module
    if decay:
        from gns.weight_average import WeightAverage
    if resumed is None:
        if cfg.train.init_from:
            from gns.fine_tune import init_from, train_collisions_only
            spec = init_from(sim, cfg.train.init_from, cfg, spec)
            if cfg.train.collisions_only:
                train_collisions_only(sim)
        return sim, optimizer, spec, 0, WeightAverage(sim, decay) if decay else None
    from gns.fine_tune import incompatibility, merge_ranges, train_collisions_only
    path, ckpt = resumed
    trained = ModelSpec.from_dict(ckpt["spec"])
    problem = incompatibility(ckpt["config"], trained, cfg, spec)
    if problem:
        raise CheckpointError(f"cannot resume {path}: {problem}")
    # with a weight average, "model" holds the average and "trained" the weights training goes on from
    sim.load_state_dict(ckpt.get(TRAINED, ckpt["model"]))
    optimizer.load_state_dict(ckpt["optimizer"])
    step = int(ckpt["step"])
    spec = merge_ranges(trained, spec)
    restore_rng(ckpt["rng"], rng)
    if cfg.train.collisions_only:
        train_collisions_only(sim)
    average = None
    if decay:
        average = WeightAverage(sim, decay, step, ckpt["model"] if TRAINED in ckpt else None)
    return sim, optimizer, spec, step, average


def _place_model(sim: LearnedSimulator, cfg: Config, device: torch.device, world: World, steps: int) -> None:
    """The simulator on its device in training mode, under bf16 autocast and compiled if asked, joined to
    the other processes' (DistributedDataParallel) when there are several; face edges' triangle
    distances compiled with `steps` >= CONTACTS_COMPILE_STEPS to go."""
    sim.to(device).train()
    sim.set_speed(cfg.train.autocast, cfg.train.compile)
    sim.compile_contacts(sim.collision_mode == "face" and steps >= CONTACTS_COMPILE_STEPS)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if world.size > 1:
        from gns.processes import distributed, start
        start(world, device)
        sim.distribute(distributed(sim.network, device))


def _train_loop(run: Path, cfg: Config, sim: LearnedSimulator, optimizer: torch.optim.Optimizer,
                tracks: ObjectTracks, valid: ObjectTracks | None, spec: ModelSpec, step: int,
                rng: np.random.Generator, device: torch.device, world: World, stale: list[Path],
                resumed_from: Path | None, provenance: dict, log: Callable[[str], None],
                average: WeightAverage | None = None, earlier_seconds: float = 0.0) -> int:
    """Steps from `step` to cfg.train.steps: a batch, an Adam step, a metrics line every
    train.log_every steps (with validation every valid.every), a checkpoint every
    train.checkpoint_every. Returns the last step. Every checkpoint records the seconds trained
    to reach it, the earlier segments' (`earlier_seconds`) included: the cost of a run that was
    stopped and resumed is in its checkpoint, not in whoever timed its last segment."""
    config_dict = config_to_dict(cfg)
    t_segment = time.perf_counter()
    if world.main:
        start_run_folder(run, stale, resumed_from, step, config_dict, provenance, log)

    def state(step: int) -> dict:
        weights = {"model": sim.state_dict()} if average is None else \
            {"model": average.state_dict(sim), TRAINED: sim.state_dict()}
        return {"format": CHECKPOINT_FORMAT, "step": step, "seed": cfg.train.seed, "config": config_dict,
                "spec": spec.to_dict(), **weights, "optimizer": optimizer.state_dict(),
                "rng": rng_state(rng), "provenance": provenance,
                TRAIN_SECONDS: round(earlier_seconds + time.perf_counter() - t_segment, 3)}

    log(_start_line(cfg, sim, tracks, spec, step, world, resumed_from))
    last_good = resumed_from
    bar = progress_bar(cfg.train.steps, step, log, enabled=world.main)
    metrics = open(run / METRICS, "a") if world.main else None
    writer = None
    if cfg.train.tensorboard and world.main:
        from gns.tensorboard_log import tensorboard_writer
        writer = tensorboard_writer(run, step + 1 if resumed_from else None)
    stop = StopRequest() if world.size == 1 else contextlib.nullcontext()
    try:
        with stop:
            step, last_good = _steps(run, cfg, sim, optimizer, tracks, valid, step, rng, device, world, state,
                                     last_good, bar, metrics, writer, stop, average)
    finally:
        bar.close()
        if metrics is not None:
            metrics.close()
        if writer is not None:
            writer.close()
    return step


def _steps(run: Path, cfg: Config, sim: LearnedSimulator, optimizer: torch.optim.Optimizer, tracks: ObjectTracks,
           valid: ObjectTracks | None, step: int, rng: np.random.Generator, device: torch.device,
           world: World, state: Callable[[int], dict], last_good: Path | None, bar, metrics, writer,
           stop, average: WeightAverage | None = None) -> tuple[int, Path | None]:
    """The loop of _train_loop; returns (step reached, last checkpoint). Stops on a signal
    (`stop.asked`) after the step under way, with a checkpoint there. Validation scores the
    weight average when there is one: the weights the checkpoints keep for use."""
    loss_sum, loss_count, busy = 0.0, 0, 0.0
    t_mark = time.perf_counter()
    while step < cfg.train.steps:
        t0 = time.perf_counter()
        lr = learning_rate(cfg, step)
        batch, fraction = _next_batch(tracks, rng, cfg, world)
        try:
            loss = train_step(sim, optimizer, batch.to(device), lr, cfg.train.grad_clip, fraction, world.size,
                              cfg.train.rigid_loss)
        except FloatingPointError as e:
            raise TrainingError(_stopped(str(e), step + 1, last_good)) from None
        if average is not None:
            average.update()
        step += 1
        busy += time.perf_counter() - t0
        loss_sum += loss
        loss_count += 1
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.4g}", lr=f"{lr:.2g}", refresh=False)

        validating = valid is not None and step % cfg.valid.every == 0
        if world.main and (step % cfg.train.log_every == 0 or validating or step == cfg.train.steps):
            entry = {"step": step, "loss": loss_sum / loss_count, "lr": lr,
                     "steps_per_sec": loss_count / busy,
                     "graphs_per_sec": loss_count * cfg.train.batch_size / busy,
                     "time": time.perf_counter() - t_mark}
            if validating:
                with average.swapped_in() if average is not None else contextlib.nullcontext():
                    entry.update(validate(sim, valid, cfg, device))
            write_metrics(metrics, writer, entry)
            loss_sum, loss_count, busy = 0.0, 0, 0.0
        if step % cfg.train.checkpoint_every == 0 or step == cfg.train.steps:
            if not all(torch.isfinite(p).all() for p in sim.parameters()):
                raise TrainingError(_stopped("a weight is not finite", step, last_good))
            if world.main:
                last_good = save_checkpoint(run, state(step), cfg.train.keep_checkpoints)
        if getattr(stop, "asked", None):
            if last_good is None or last_good.name != f"ckpt-{step:06d}.pt":
                last_good = save_checkpoint(run, state(step), cfg.train.keep_checkpoints)
            raise TrainingInterrupted(f"{stop.asked}: stopped at step {step} of {cfg.train.steps}, "
                                      f"checkpoint saved; resume with the same command and --resume")
    return step, last_good


def _start_line(cfg: Config, sim: LearnedSimulator, tracks: ObjectTracks, spec: ModelSpec, step: int,
                world: World, resumed_from: Path | None) -> str:
    """The log's first line: what is trained on what."""
    n_params = sum(p.numel() for p in sim.parameters())
    contact = ""
    if tracks.contact is not None:
        # the drawn share comes on top of the contact windows among the rest, drawn from all
        natural, f = float(tracks.contact.double().mean()), cfg.train.contact_fraction
        kind = "with objects near each other" if cfg.train.contact_kind == "objects" else "in contact"
        contact = f" ({natural:.0%} {kind}, {f + (1 - f) * natural:.0%} of each batch: {f:.0%} drawn from them)"
    trained = sum(p.numel() for p in sim.parameters() if p.requires_grad)
    frozen = f" ({trained} taking gradients: train.collisions_only)" if cfg.train.collisions_only else ""
    processes = f" on {world.size} processes" if world.size > 1 else ""
    precision = f", network in {'bf16' if sim.autocast_used == 'bf16' else 'float32'} (autocast auto, measured)" \
        if cfg.train.autocast == "auto" else ""
    return (f"{'resuming' if resumed_from else 'training'} at step {step} of {cfg.train.steps}{processes}: "
            f"{tracks.num_windows} windows{contact} from {tracks.num_scenes} train scenes, {n_params} parameters{frozen}, "
            f"node features {list(spec.node_features)}, edge features {list(spec.edge_features)}{precision}")


def _next_batch(tracks: ObjectTracks, rng: np.random.Generator, cfg: Config, world: World) -> tuple[Batch, float]:
    """The next global batch of windows, augmented, or this process's share of it (gns.processes.share),
    and the fraction of the global batch's nodes that share holds."""
    batch = tracks.sample(rng, cfg.train.batch_size, cfg.augment.rotate, cfg.augment.noise_std,
                          cfg.augment.vertex_noise, cfg.augment.track_noise,
                          cfg.train.contact_fraction, cfg.augment.mirror,
                          cfg.augment.body_symmetry)
    if world.size == 1:
        return batch, 1.0
    from gns.processes import share, windows
    nodes = batch.graph.num_nodes
    batch = windows(batch, *share(cfg.train.batch_size, world))
    return batch, batch.graph.num_nodes / nodes


def _stopped(what: str, step: int, last_good: Path | None) -> str:
    kept = f"the last good checkpoint is {last_good}" if last_good else "no checkpoint was written yet"
    return f"{what} at step {step}; training stopped, {kept}"


# One optimiser step and its validation: the learning rate by step, the per-node MSE averaged over
# pushforward steps, one Adam step, and the validation loss and short rollouts.


def learning_rate(cfg: Config, step: int) -> float:
    """lr_final + (lr_init - lr_final) * 0.1^(step / lr_decay_steps), as learning_to_simulate."""
    t = cfg.train
    return t.lr_final + (t.lr_init - t.lr_final) * 0.1 ** (step / t.lr_decay_steps)


def train_step(sim: LearnedSimulator, optimizer: torch.optim.Optimizer, batch: Batch, lr: float,
               grad_clip: float, fraction: float = 1.0, processes: int = 1, rigid_loss: float = 0.0) -> float:
    """One Adam step on the per-node MSE of a batch; returns the loss.

    On several processes `batch` is this process's share of the global batch, holding
    `fraction` of its nodes. Each process weights its mean by fraction x processes, so the
    average of the gradients (DistributedDataParallel) is the gradient of the global batch's
    per-node mean, as one process training on the whole batch; the returned loss is that mean.
    Raises FloatingPointError, before the weights change, if the loss or the gradient is not finite.
    """
    for group in optimizer.param_groups:
        group["lr"] = lr
    loss = unrolled_loss(sim, batch, rigid_loss)
    if processes > 1:
        # every process sees the same global loss, so all stop together on a NaN
        from gns.processes import sum_over_processes
        total = sum_over_processes(loss.detach() * fraction)
        loss = loss * (fraction * processes)
    else:
        total = loss
    if not torch.isfinite(total):
        raise FloatingPointError(f"the loss is {total.item()}")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    norm = torch.nn.utils.clip_grad_norm_(sim.parameters(), grad_clip or math.inf, foreach=True)  # 1.3x on ~200 grads
    if not torch.isfinite(norm):
        raise FloatingPointError(f"the gradient norm is {norm.item()}")
    optimizer.step()
    return total.item()


def unrolled_loss(sim: LearnedSimulator, batch: Batch, rigid_loss: float = 0.0) -> torch.Tensor:
    """The one-step loss, averaged over the batch's target frames (pushforward training).

    Step k > 1 starts from the model's own earlier predictions, shape-matched as in rollouts and
    detached: the model learns to correct the errors it makes itself (after a bounce, say),
    without backpropagating through time. Each step's target is the true frame, so the
    acceleration asked for pulls a drifted prediction back toward the truth."""
    targets = batch.targets
    frames = list(batch.history.unbind(1))
    total = 0.0
    for k in range(targets.shape[1]):
        history = torch.stack(frames[-HISTORY:], dim=1)
        # the next input from this step's own forward pass: predict_next's, without a second pass
        following: list | None = [] if k + 1 < targets.shape[1] else None
        total = total + sim.loss(history, targets[:, k], batch.graph, rigid_loss, following)
        if following is not None:
            g = batch.graph
            frames.append(shape_match_packed(following[0], g.rest, g.node_graph, g.num_graphs)[2])
    return total / targets.shape[1]


@torch.no_grad()
def validate(sim: LearnedSimulator, valid: ObjectTracks, cfg: Config, device: torch.device) -> dict:
    """One-step loss on evenly spaced valid windows; centre error of short shape-matched rollouts."""
    sim.eval()
    try:
        n = min(cfg.valid.windows, valid.num_windows)
        windows = torch.linspace(0, valid.num_windows - 1, n).round().long().unique()
        total, nodes = 0.0, 0
        for chunk in windows.split(cfg.train.batch_size):
            batch = valid.batch(chunk).to(device)
            total += float(sim.loss(batch.history, batch.target, batch.graph)) * batch.graph.num_nodes
            nodes += batch.graph.num_nodes
        out = {"valid_loss": total / nodes}
        tracks = torch.nonzero(valid.track_scene < cfg.valid.rollout_scenes)[:, 0]
        if len(tracks):
            out.update(_rollout_error(sim, valid, tracks, cfg.valid.rollout_steps, device))
        return out
    finally:
        sim.train()


def _rollout_error(sim: LearnedSimulator, valid: ObjectTracks, tracks: torch.Tensor, max_steps: int,
                   device: torch.device) -> dict:
    """Mean distance (scene units) between predicted and true centres over a rollout from 3 true frames."""
    steps = min(max_steps, int(valid.length[tracks].min()) - HISTORY)
    graph, verts, centres = valid.track_vertices(tracks, HISTORY + steps)
    graph = graph.to(device)
    pred = sim.rollout(verts[:, :HISTORY].to(device), graph, steps)
    pred_centres = torch.stack([shape_match_packed(x, graph.rest, graph.node_graph, graph.num_graphs)[1]
                                for x in pred], dim=1).cpu()
    error = (pred_centres - centres[:, HISTORY:]).norm(dim=-1).mean(dim=1)       # (B,)
    finite = torch.isfinite(error)
    # A diverged track is counted, not averaged in, so the log stays valid JSON and comparable.
    return {"valid_rollout_position_error": float(error[finite].mean()) if finite.any() else None,
            "valid_rollout_diverged": int((~finite).sum()), "valid_rollout_steps": steps}
