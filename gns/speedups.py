"""Two ways the network runs faster, each loaded only when asked for: bfloat16 autocast, where it
pays on this machine, and torch.compile.

bfloat16 pays on some CPUs and costs on others with the same instruction-set flags: on one AMD
EPYC (avx512_bf16) bf16 + compile trained `gns_cpu` 1.76x as fast as float32; on an Intel
Xeon (avx512_bf16, no AMX) a bf16 matrix product of the network's shapes
ran 1.8x slower than float32 (experiments/log.md). No flag tells them apart, so `auto` times one
such product in both types, once per process and shape, and picks bf16 only when it is clearly
faster. Off a CPU (CUDA) `auto` takes bf16 where the device supports it.
"""
from __future__ import annotations

import os
import time
import types
import warnings
from pathlib import Path

import torch
from torch import nn

CHOICES = ("none", "bf16", "auto")
# bf16 must be this much faster: autocast adds casts that the product alone does not show
MARGIN = 1.15
# bf16 asked for by name but this much slower than float32 earns a warning: a CPU without native
# bfloat16 emulates it (an AMD EPYC without avx512: rollouts 12-14x slower), where `auto`
# would have kept float32
SLOW = 0.5
_cache: dict[tuple, float] = {}
# the instruction-set features a speed figure must name: bf16 runs natively only with avx512_bf16
# or AMX, and float32's speed follows the vector width
CPU_FEATURES = ("avx2", "avx512f", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16")


def cpu_info() -> dict:
    """This CPU's model, cores and which of CPU_FEATURES it has (Linux's /proc/cpuinfo; elsewhere
    the platform's name and no features)."""
    first: dict[str, str] = {}   # every core repeats its block: the first one's fields
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            first.setdefault(key.strip(), value.strip())
    except OSError:
        import platform
        first["model name"] = platform.processor() or platform.machine()
    flags = set(first.get("flags", "").split())
    return {"cpu": first.get("model name", "unknown CPU"), "cores": os.cpu_count(),
            "features": [f for f in CPU_FEATURES if f in flags]}


def cpu_line() -> str:
    """One line for a benchmark's head: the CPU, its features and torch's view of them."""
    c = cpu_info()
    bf16 = torch.ops.mkldnn._is_mkldnn_bf16_supported()
    return (f"processor: {c['cpu']}, {c['cores']} cores; features: {', '.join(c['features']) or 'none of ' + ', '.join(CPU_FEATURES)}; "
            f"torch {torch.__version__} (capability {torch.backends.cpu.get_cpu_capability()}, oneDNN bf16 "
            f"{'yes' if bf16 else 'no'})")


def bf16_speedup(width: int, rows: int = 4096, repeats: int = 5, device: str | torch.device = "cpu") -> float:
    """float32 time / bfloat16 time of a (rows, 3 width) x (3 width, width) matrix product, the
    shape of the network's first edge layer (best of `repeats`, each several products);
    cached per (width, rows, device, threads)."""
    device = torch.device(device)
    key = (width, rows, str(device), torch.get_num_threads())
    if key not in _cache:
        a = torch.randn(rows, 3 * width, device=device)
        w = torch.randn(3 * width, width, device=device)
        times = {}
        for dtype in (torch.float32, torch.bfloat16):
            x, y = a.to(dtype), w.to(dtype)
            x @ y  # warm-up: first-call costs are not the product's
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                for _ in range(4):
                    x @ y
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                best = min(best, time.perf_counter() - t0)
            times[dtype] = best
        _cache[key] = times[torch.float32] / times[torch.bfloat16]
    return _cache[key]


def resolve_autocast(name: str, width: int, device: str | torch.device = "cpu", measure=bf16_speedup) -> str:
    """'none' or 'bf16' for `name` ('none', 'bf16' or 'auto'); 'auto' measures (measure(width,
    device=...) -> float32 / bf16 time) and takes bf16 when it is at least MARGIN times faster.
    'bf16' on a CPU is kept but measured too, with a warning where it is less than SLOW times as fast."""
    if name not in CHOICES:
        raise ValueError(f"autocast must be one of {', '.join(CHOICES)}, got {name!r}")
    device = torch.device(device)
    if name == "bf16" and device.type == "cpu":
        ratio = measure(width, device=device)
        if ratio < SLOW:
            warnings.warn(f"bf16 autocast measures {1 / ratio:.0f}x slower than float32 on this CPU (no native "
                          "bfloat16): --autocast auto would keep float32 here", stacklevel=2)
    if name != "auto":
        return name
    if device.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "none"
    return "bf16" if measure(width, device=device) >= MARGIN else "none"


class _OwnCode(nn.Module):
    """The network as torch.compile should see it (LearnedSimulator.set_speed). torch.compile caches compiled code
    per code object, up to dynamo's recompile_limit (8) entries, then runs eager, silently; the
    network's own forward is one code object for every model of the class. So two compiles of one
    network (frozen for rollouts, unfrozen for training) would share graphs, whichever came first,
    and the ninth compiled model of a process (an ensemble, a benchmark, a script scoring many
    runs; found scoring 12 in one) ran eager. Each instance's forward is a code object of its own."""

    def __init__(self, network: nn.Module):
        super().__init__()
        self.network = network
        f = type(self)._forward
        self.forward = types.MethodType(types.FunctionType(f.__code__.replace(), f.__globals__, "forward"), self)

    def _forward(self, *args: torch.Tensor) -> torch.Tensor:
        return self.network(*args)


def compiled(network: nn.Module) -> nn.Module:
    """The network through torch.compile, with dynamic shapes (every batch has its own node and
    edge counts) and a code object of its own (_OwnCode). On a CPU without a C++ compiler, which
    inductor needs, the network itself with a warning: the same results, only slower, where
    torch.compile would fail at the first call."""
    device = next(network.parameters()).device
    if device.type == "cpu" and not cpp_compiler():
        warnings.warn("compile asked for, but this machine has no C++ compiler (g++, c++, clang++, cl or $CXX), "
                      "which torch.compile needs on a CPU: the network runs uncompiled", stacklevel=2)
        return network
    return torch.compile(_OwnCode(network), dynamic=True)


def cpp_compiler() -> str | None:
    """The C++ compiler inductor would find, or None."""
    import shutil
    names = [os.environ["CXX"]] if os.environ.get("CXX") else []
    return next((path for name in (*names, "g++", "c++", "clang++", "cl") if (path := shutil.which(name))), None)
