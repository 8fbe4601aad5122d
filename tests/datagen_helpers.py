"""Scenes built by hand (exact pose, no sampling) for physics tests."""
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
