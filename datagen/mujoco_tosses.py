"""`datagen toss --engine mujoco`: cube tosses simulated by MuJoCo at a chosen contact stiffness.

One cube of the real ContactNets set-up, in its units (half-widths, seconds, 148 frames/s), is
tossed onto a table from a start drawn from a distribution fitted to the real tosses
(configs/mujoco_cubes.toml [start]); MuJoCo simulates the whole toss, frame 0 included. The
contact is MuJoCo's soft constraint: solref (timeconst, dampratio), a damped spring reaching the
surface in about timeconst seconds, so the stiffness levels (hard, medium, soft) are time
constants. The world: a plane and a box (a uniform solid cube's inertia) with one explicit
contact pair carrying every contact setting (condim 3, sliding friction), physics at
frame_rate x substeps Hz with the Euler integrator and the Newton solver.

The output is the project's shard format (docs/data_format.md) like any toss: scene i of split s
is drawn from numpy.random.default_rng([seed, s, i]), so the same seed gives the same tosses, and
the first n training tosses of a larger dataset are the n tosses of a smaller one. MuJoCo is the
optional [mujoco] extra, imported only here.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from plumbing import ConfigError, DataError, check_output_folder, config_dir, load_toml

from . import __version__
from .scenes import apply_sets, get_shape

from .shards import SPLITS, Scene, clear_dataset, continuous, rotation, shard_name, write_metadata, write_shard, wxyz

PRESET = "mujoco_cubes"
MISSING = "datagen toss --engine mujoco needs the mujoco package: pip install -e '.[mujoco]'"
MATERIAL = "mujoco"


def load_config(path: str | Path | None = None, sets: list[str] | None = None,
                stiffness: str | None = None) -> dict:
    """configs/mujoco_cubes.toml, a user TOML and --set overrides on top, the stiffness level
    (a key of [levels]) resolved into contact.timeconst."""
    cfg = load_toml(config_dir() / f"{PRESET}.toml")
    if path is not None:
        from .scenes import merge
        cfg = merge(cfg, load_toml(path))
    cfg = apply_sets(cfg, list(sets or []) + ([f'contact.stiffness="{stiffness}"'] if stiffness else []))
    level = cfg["contact"]["stiffness"]
    if level not in cfg["levels"]:
        raise ConfigError(f"unknown stiffness {level!r}: one of {', '.join(cfg['levels'])}")
    cfg["contact"]["timeconst"] = float(cfg["levels"][level])
    _validate(cfg)
    return cfg


def _validate(cfg: dict) -> None:
    c, s = cfg["contact"], cfg["start"]
    positive = {"scene.frame_rate": cfg["scene"]["frame_rate"], "contact.timeconst": c["timeconst"],
                "contact.dampratio": c["dampratio"], "cube.half_width": cfg["cube"]["half_width"],
                "cube.mass": cfg["cube"]["mass"]}
    for key, v in positive.items():
        if not (math.isfinite(float(v)) and float(v) > 0):
            raise ConfigError(f"config key {key!r} must be finite and > 0, got {v!r}")
    if int(cfg["scene"]["frames"]) < 4:
        raise ConfigError(f"scene.frames must be >= 4 (a GNS window needs 4), got {cfg['scene']['frames']}")
    if int(cfg["physics"]["substeps"]) < 1:
        raise ConfigError("physics.substeps must be >= 1")
    if float(c["friction"]) < 0 or len(c["solimp"]) != 3:
        raise ConfigError("contact.friction must be >= 0 and contact.solimp hold 3 numbers")
    for k in ("position_mean", "position_std", "angular_velocity_mean", "angular_velocity_std"):
        if len(s[k]) != 3:
            raise ConfigError(f"start.{k} must hold 3 numbers")


def model_xml(cfg: dict) -> str:
    c, half = cfg["contact"], float(cfg["cube"]["half_width"])
    dt = 1.0 / (float(cfg["scene"]["frame_rate"]) * int(cfg["physics"]["substeps"]))
    mu = float(c["friction"])
    dmin, dmax, width = (float(x) for x in c["solimp"])
    return f"""<mujoco model="cube toss">
  <option timestep="{dt!r}" gravity="0 0 {-float(cfg['physics']['gravity'])!r}" cone="elliptic" integrator="Euler"/>
  <worldbody>
    <geom name="table" type="plane" size="0 0 1" contype="0" conaffinity="0"/>
    <body name="cube">
      <freejoint/>
      <geom name="cube" type="box" size="{half!r} {half!r} {half!r}" mass="{float(cfg['cube']['mass'])!r}"
            contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="cube" geom2="table" condim="3" friction="{mu!r} {mu!r} 0 0 0"
          solref="{float(c['timeconst'])!r} {float(c['dampratio'])!r}" solimp="{dmin!r} {dmax!r} {width!r} 0.5 2"/>
  </contact>
</mujoco>"""


def _mujoco():
    try:
        import mujoco
    except ImportError:
        raise DataError(MISSING) from None
    return mujoco


def sample_start(cfg: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(position, quaternion w x y z, velocity, world angular velocity) of a toss's frame 0, drawn
    from the fitted distribution of configs/mujoco_cubes.toml [start]."""
    s = cfg["start"]
    heading = rng.uniform(0.0, 2.0 * np.pi)
    p = rng.normal(s["position_mean"], s["position_std"])
    v = np.array([rng.normal(s["speed_mean"], s["speed_std"]), 0.0,
                  rng.normal(s["vertical_velocity_mean"], s["vertical_velocity_std"])])
    w = rng.normal(s["angular_velocity_mean"], s["angular_velocity_std"])
    turn = Rotation.from_rotvec([0.0, 0.0, heading])
    p, v, w = turn.apply(p), turn.apply(v), turn.apply(w)
    q = Rotation.random(random_state=rng)
    half = float(cfg["cube"]["half_width"])
    corners = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    lowest = p[2] + q.apply(corners)[:, 2].min()
    if lowest < float(s["clearance"]):
        p[2] += float(s["clearance"]) - lowest
    return p, wxyz(q.as_quat()), v, w


def simulate_toss(cfg: dict, start, model=None) -> Scene:
    """One toss from `start` (sample_start's tuple): every frame simulated by MuJoCo."""
    mujoco = _mujoco()
    m = model if model is not None else mujoco.MjModel.from_xml_string(model_xml(cfg))
    d = mujoco.MjData(m)
    p, q, v, w = (np.asarray(x, np.float64) for x in start)
    d.qpos[:] = np.concatenate([p, q])
    d.qvel[:] = np.concatenate([v, rotation(q).inv().apply(w)])  # a free joint's spin is in the body frame
    T, substeps = int(cfg["scene"]["frames"]), int(cfg["physics"]["substeps"])
    pos, quat, vel, ang = np.empty((T, 1, 3)), np.empty((T, 1, 4)), np.empty((T, 1, 3)), np.empty((T, 1, 3))
    for t in range(T):
        if t:
            mujoco.mj_step(m, d, nstep=substeps)
        qt = d.qpos[3:7] / np.linalg.norm(d.qpos[3:7])
        pos[t, 0], quat[t, 0], vel[t, 0] = d.qpos[:3], qt, d.qvel[:3]
        ang[t, 0] = rotation(qt).apply(d.qvel[3:6])
    if not np.isfinite(pos).all():
        raise DataError("MuJoCo diverged (non-finite positions): lower contact.timeconst's substep ratio")
    c = cfg["contact"]
    return Scene(positions=pos, quaternions=continuous(quat), velocities=vel, angular_velocities=ang,
                 shape=["cube"], material=[MATERIAL], scale=np.array([2.0 * float(cfg["cube"]["half_width"])]),
                 mass=np.array([float(cfg["cube"]["mass"])]), friction=np.array([float(c["friction"])]),
                 restitution=np.array([0.0]), attrs={})


def _shard_tosses(job: tuple) -> list[Scene]:
    """One shard's tosses (cfg, seed, split index, split, first, end), each from its own RNG key:
    the same scenes on any worker. A worker process builds its own model (MjModel is not shared)."""
    cfg, seed, s_index, split, first, end = job
    model = _mujoco().MjModel.from_xml_string(model_xml(cfg))
    scenes = []
    for i in range(first, end):
        sc = simulate_toss(cfg, sample_start(cfg, np.random.default_rng([seed, s_index, i])), model)
        sc.attrs = {"scene_id": f"{split}-{i}", "seed": [seed, s_index, i], "index": i}
        scenes.append(sc)
    return scenes


def generate_tosses(cfg: dict, seed: int, counts: dict[str, int], out: str | Path, overwrite: bool = False,
                    per_shard: int = 250, progress: bool = False, workers: int = 1) -> dict:
    """Simulate counts[split] tosses per split into the dataset folder `out`; returns its metadata.
    Shards are simulated on `workers` processes (the output does not depend on it), written
    atomically in order, metadata.json last (a dataset is complete or absent: an interrupted run
    removes its shards)."""
    if workers < 1:
        raise DataError(f"--workers must be >= 1, got {workers}")
    mujoco = _mujoco()
    out = Path(out)
    if sum(counts.values()) < 1:
        raise DataError("no tosses to make: give --scenes, --valid or --test")
    check_output_folder(out, overwrite, "use --overwrite to replace it")
    out.mkdir(parents=True, exist_ok=True)
    if overwrite:
        clear_dataset(out)
    shape = get_shape("cube")
    meshes = {"cube": (shape.vertices, shape.faces)}
    from tqdm import tqdm
    jobs = [(cfg, seed, s_index, split, first, min(int(counts[split]), first + per_shard), k)
            for s_index, split in enumerate(SPLITS) if int(counts.get(split, 0)) > 0
            for k, first in enumerate(range(0, int(counts[split]), per_shard))]
    splits = {split: {"num_scenes": int(counts[split]), "shards": []} for _, _, _, split, *_ in jobs}
    bar = tqdm(total=sum(counts.values()), desc="mujoco tosses", unit="toss", disable=not progress)
    pool = None
    if workers > 1:
        import multiprocessing
        pool = multiprocessing.get_context("spawn").Pool(workers)
    try:
        done = (pool.imap if pool else map)(_shard_tosses, [j[:6] for j in jobs])
        for (_, _, _, split, first, _, k), scenes in zip(jobs, done):
            name = shard_name(split, k)
            write_shard(out / name, scenes, meshes, attrs={"split": split, "shard": k, "seed": seed,
                                                           "first_scene": first, "source": "mujoco"})
            splits[split]["shards"].append(name)
            bar.update(len(scenes))
    except BaseException:
        # stopped (Ctrl-C, SIGTERM) or failed: shards without metadata.json are no dataset, and
        # tosses are quick to make again, so nothing is kept
        if pool:
            pool.terminate()
            pool = None
        bar.close()
        clear_dataset(out)
        raise
    finally:
        if pool:
            pool.terminate()
    bar.close()
    fr, substeps = float(cfg["scene"]["frame_rate"]), int(cfg["physics"]["substeps"])
    meta = {"complete": True, "generator": "datagen toss --engine mujoco", "generator_version": __version__,
            "engine": {"name": "mujoco", "version": mujoco.__version__}, "seed": int(seed), "config": cfg,
            "units": "cube half-widths (1 = 0.0524 m), the real ContactNets cube's",
            "frame_rate": fr, "physics_rate": fr * substeps, "steps_per_frame": substeps,
            "num_frames": int(cfg["scene"]["frames"]), "gravity": [0.0, 0.0, -float(cfg["physics"]["gravity"])],
            "floor": {"z": 0.0, "friction": float(cfg["contact"]["friction"]), "restitution": 0.0},
            "materials_vary": False, "quaternion_order": "wxyz", "soft_contact": True,
            "shapes": {"cube": {"num_vertices": int(len(shape.vertices)), "num_faces": int(len(shape.faces))}},
            "splits": splits}
    return write_metadata(out, meta)


def dataset_penetration(scenes: list[Scene], floor_z: float = 0.0) -> dict:
    """How deep the cube sinks into the table, % of its width: the mean over frames (as the
    ContactNets penetration metric averages it), the deepest frame, and at rest (the last 10
    frames), each averaged over tosses."""
    mean, deepest, rest = [], [], []
    for sc in scenes:
        width = float(sc.scale[0])
        corners = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)]) * width
        R = rotation(sc.quaternions[:, 0]).as_matrix()                       # (T, 3, 3)
        low = (np.einsum("tij,vj->tvi", R, corners)[..., 2] + sc.positions[:, 0, 2:3]).min(axis=1)
        pen = 100.0 * np.maximum(0.0, floor_z - low) / width
        mean.append(pen.mean())
        deepest.append(pen.max())
        rest.append(pen[-10:].mean())
    return {"mean_pct": float(np.mean(mean)), "max_pct": float(np.mean(deepest)), "rest_pct": float(np.mean(rest)),
            "num_tosses": len(scenes)}


def fit_starts(scenes: list[Scene], frame_rate: float, gravity: float) -> dict:
    """The [start] distribution of configs/mujoco_cubes.toml fitted to real one-cube tosses (e.g.
    the ContactNets ones, datagen.contactnets): each toss's state at frame 2 estimated from frames
    0-2 by free flight (as baselines.toss.initial_state does), turned into its heading frame (x
    along the horizontal velocity); means and standard deviations of each component."""
    if len(scenes) < 2:
        raise DataError("fitting a start distribution needs at least 2 tosses")
    dt, rows = 1.0 / frame_rate, []
    for sc in scenes:
        if sc.num_frames < 3:
            raise DataError("a toss of fewer than 3 frames has no start state")
        p, q = sc.positions[:3, 0], sc.quaternions[:3, 0]
        v = (p[2] - p[0]) / (2 * dt) + np.array([0.0, 0.0, -gravity]) * dt
        w = (rotation(q[2]) * rotation(q[0]).inv()).as_rotvec() / (2 * dt)
        turn = Rotation.from_rotvec([0.0, 0.0, -math.atan2(v[1], v[0])])
        rows.append(np.concatenate([turn.apply(p[2]), turn.apply(v), turn.apply(w)]))
    r = np.array(rows)
    mean, std = r.mean(0), r.std(0)

    def rounded(a):
        return [round(float(x), 2) for x in a]
    return {"position_mean": rounded(mean[:3]), "position_std": rounded(std[:3]),
            "speed_mean": round(float(mean[3]), 2), "speed_std": round(float(std[3]), 2),
            "vertical_velocity_mean": round(float(mean[5]), 2), "vertical_velocity_std": round(float(std[5]), 2),
            "angular_velocity_mean": rounded(mean[6:]), "angular_velocity_std": rounded(std[6:]),
            "num_tosses": len(scenes)}
