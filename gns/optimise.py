"""One optimiser step of the training and its validation: the learning rate as a function of the
step, the per-node MSE averaged over pushforward steps, one Adam step, and the validation loss and
short rollouts."""
from __future__ import annotations

import math

import torch

from gns import hardware
from gns.config import Config
from gns.data import Batch, ObjectTracks
from gns.features import HISTORY
from gns.geometry import shape_match_packed
from gns.simulator import LearnedSimulator


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
        total = hardware.sum_over_processes(loss.detach() * fraction)
        loss = loss * (fraction * processes)
    else:
        total = loss
    if not torch.isfinite(total):
        raise FloatingPointError(f"the loss is {total.item()}")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    norm = torch.nn.utils.clip_grad_norm_(sim.parameters(), grad_clip or math.inf)
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
        total = total + sim.loss(history, targets[:, k], batch.graph, rigid_loss)
        if k + 1 < targets.shape[1]:
            with torch.no_grad():
                x = sim.predict_next(*frames[-HISTORY:], batch.graph)
                x = shape_match_packed(x, batch.graph.rest, batch.graph.node_graph, batch.graph.num_graphs)[2]
            frames.append(x)
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
