"""Torch devices by name, checked before any work: one line for a user, not torch's assertion.
Training and inference both read them, so neither imports the other for it."""
from __future__ import annotations

import torch

from gns.config import ConfigError


def parse_device(name: str, what: str = "train.device") -> torch.device:
    """A device name as a torch device, checked before any work: one line, not torch's assertion."""
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"{what}={name!r} is not a torch device; use 'cpu' or 'cuda'") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{what}={name} but CUDA is not available in this torch build "
                          f"(torch {torch.__version__}); use {what}=cpu")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise ConfigError(f"{what}={name} but this machine has {torch.cuda.device_count()} CUDA device(s)")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ConfigError(f"{what}={name} but MPS is not available here; use {what}=cpu")
    if device.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(f"{what}={name}: only cpu, cuda and mps are supported")
    return device
