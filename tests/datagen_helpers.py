"""Scenes built by hand (exact pose, no sampling) for physics tests, and a toss stopped midway."""
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from datagen.scenes import load_config
from datagen.scenes import ObjectSpec, SceneSpec
from datagen.scenes import get_shape


def config(frame_rate=12, frames=24, **sets):
    extra = [f"{k.replace('__', '.')}={v}" for k, v in sets.items()]
    return load_config(sets=[f"scene.frame_rate={frame_rate}", f"scene.frames={frames}", *extra])


def one_object(cfg, shape="sphere", material="rubber", scale=1.0, position=(0, 0, 2), quaternion=(1, 0, 0, 0),
               velocity=(0, 0, 0), angular_velocity=(0, 0, 0)) -> SceneSpec:
    s = get_shape(shape)
    mat = cfg["materials"][material]
    obj = ObjectSpec(shape=shape, size="custom", scale=scale, material=material, friction=mat["friction"],
                     restitution=mat["restitution"], density=mat["density"], mass=s.mass(mat["density"], scale),
                     inertia=s.inertia_diagonal(mat["density"], scale), position=np.array(position, float),
                     quaternion=np.array(quaternion, float), velocity=np.array(velocity, float),
                     angular_velocity=np.array(angular_velocity, float))
    return SceneSpec(seed=0, split="train", index=0, objects=[obj])


def sigterm_toss(out: Path, *args: str, shards: int = 1) -> tuple[int, str]:
    """`datagen toss --out OUT ARGS` in a process of its own, sent SIGTERM once `shards` shards
    are in OUT (its workers busy); returns its exit status and stderr."""
    proc = subprocess.Popen([sys.executable, "-m", "datagen.cli", "toss", "--out", str(out), *args],
                            cwd=Path(__file__).resolve().parents[1], stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while len(list(out.glob("*.h5"))) < shards:
        assert time.monotonic() - t0 < 300 and proc.poll() is None
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err
