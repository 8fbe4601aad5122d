"""An exponential moving average of the network's weights during training (`train.ema_decay`).

The weights a run saves for use ("model" in its checkpoints: what `gns eval`, `gns export`,
`train.init_from` and ensembles read) are then the average, while training goes on from
its own weights (kept as "trained", which `gns export` drops). Averaging the last few thousand
steps' weights smooths the step-to-step noise of Adam at a learning rate kept from decaying to
nothing (`train.lr_final`); at the end of a fully decayed run the weights no longer move and the
average changes nothing (experiments/log.md, measured both ways).

Only parameters are averaged: buffers (the normalisers' running statistics) are the trained
model's own, since the average must read its inputs in the same units as the network being trained.
"""
from __future__ import annotations

from contextlib import contextmanager

import torch

# The early steps' weights are far from the last ones: a fixed decay would keep the random start
# in the average for ~1 / (1 - decay) steps. min(decay, (1 + n) / (10 + n)) after n updates, as is
# usual, lets the average follow closely at first.
WARMUP = 10


def decay_at(decay: float, updates: int) -> float:
    """The decay used for the update after `updates` earlier ones."""
    return min(decay, (1 + updates) / (WARMUP + updates))


class WeightAverage:
    """The running average of a module's parameters; `updates` counts the updates so far (the
    training step, so that a resumed run continues the same sequence)."""

    def __init__(self, module: torch.nn.Module, decay: float, updates: int = 0,
                 saved: dict[str, torch.Tensor] | None = None):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.updates = updates
        named = list(module.named_parameters())
        self.names = [n for n, _ in named]
        self.params = [p for _, p in named]
        if saved is None:
            self.average = [p.detach().clone() for p in self.params]
        else:
            missing = [n for n in self.names if n not in saved]
            if missing:
                raise KeyError(f"the saved average lacks {missing[0]}")
            self.average = [saved[n].detach().clone().to(p.device, p.dtype) for n, p in zip(self.names, self.params)]

    @torch.no_grad()
    def update(self) -> None:
        weight = 1.0 - decay_at(self.decay, self.updates)
        for avg, p in zip(self.average, self.params):
            avg.lerp_(p.detach(), weight)
        self.updates += 1

    def state_dict(self, module: torch.nn.Module) -> dict[str, torch.Tensor]:
        """The module's state dict with the averaged parameters in place of its own."""
        state = module.state_dict()
        for name, avg in zip(self.names, self.average):
            state[name] = avg.detach().clone()
        return state

    @contextmanager
    def swapped_in(self):
        """The module runs on the averaged parameters inside the block (validation), on its own after."""
        with torch.no_grad():
            own = [p.detach().clone() for p in self.params]
            for p, avg in zip(self.params, self.average):
                p.copy_(avg)
        try:
            yield
        finally:
            with torch.no_grad():
                for p, mine in zip(self.params, own):
                    p.copy_(mine)
