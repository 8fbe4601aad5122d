"""`datagen toss`: MOVi-A scenes simulated in PyBullet and written as shards, a shard a task, on
worker processes or a Ray cluster (datagen/ray_backend.py, loaded only when asked for).

This is the one place that sets up PyBullet. Settings follow Kubric's MOVi worker: a fresh
client per scene (a reused world loses bit-exact repeatability), contactProcessingThreshold=0
per body (without it bounces die), no restitution velocity threshold, no warm starting, split
impulse, no contact slop, deterministic overlapping pairs, no damping, and the mesh's true
inertia (Bullet would otherwise replace it with a box approximation). baselines.pybullet builds
its cube-toss worlds with `new_world` and `add_floor` too.

A shard is the unit of work and of writing: its content depends only on (config, seed, split,
shard index), never on the worker count, the backend or how the shards are divided among runs
(--shard-index/--num-shards, datagen/shared_output.py). Every run claims the output folder
first and records each shard's checksum before the shard is in place (datagen/output.py), so
runs started together cannot mix two plans.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import sys
from contextlib import nullcontext
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import __version__
from plumbing import DataError, leave_signals_to_parent
from .output import (Busy, ShardTask, check_output, claim, commit_shard, finalise, plan, plan_of, start_output,
                     temporaries_removed_on_failure)
from .scenes import FLOOR_HALF_WIDTH, SceneSpec, check_floor_covers, get_shape, sample_scene
from .shards import SPLITS, Scene, continuous, shard_image, write_error, wxyz, xyzw


def _import_pybullet_quietly():
    # PyBullet prints its build time on stderr at import; keep stderr for our progress bar and
    # one-line errors.
    sys.stderr.flush()
    fd = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            import pybullet
    finally:
        os.dup2(fd, 2)
        os.close(fd)
    return pybullet


pb = _import_pybullet_quietly()


def off_floor(scene) -> list[tuple[int, int]]:
    """(object, first frame) for objects whose centre left the physics floor's extent."""
    out = []
    beyond = (np.abs(scene.positions[..., :2]) > FLOOR_HALF_WIDTH).any(axis=-1)   # (T, N)
    for n in np.flatnonzero(beyond.any(axis=0)):
        out.append((int(n), int(np.argmax(beyond[:, n]))))
    return out


_HEAP_KEPT = False


def keep_freed_memory() -> None:
    """Let this process's C heap keep what it frees instead of handing it back to the system.

    A fresh client per scene allocates and frees tens of MB; glibc returns freed memory at the
    top of the heap (and every block above its mmap threshold) to the kernel at once, so the next
    scene page-faults it all in again. That cost 15 ms a scene against 2.5 ms with the memory
    kept (MOVi-A scenes, one object, 240 Hz; benchmarks/bench_datagen.py has the before/after).
    Raising glibc's trim and mmap thresholds keeps it (results are byte-identical either way).
    Once per process; not glibc: nothing; DATAGEN_KEEP_HEAP=0 in the environment: glibc's
    defaults (the benchmark's "before")."""
    global _HEAP_KEPT
    if _HEAP_KEPT:
        return
    _HEAP_KEPT = True
    if not sys.platform.startswith("linux") or os.environ.get("DATAGEN_KEEP_HEAP") == "0":
        return
    try:
        import ctypes
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 32 * 1024 * 1024)
        libc.mallopt(m_trim_threshold, 256 * 1024 * 1024)
    except (OSError, AttributeError):  # another C library: its own behaviour, untouched
        pass


def new_world(gravity, time_step: float, solver_iterations: int, split_impulse_all: bool = True,
              client: int | None = None) -> int:
    """A new DIRECT client with the engine settings above; returns its id. split_impulse_all=False
    leaves Bullet's own split-impulse penetration threshold, as Kubric does (physics.split_impulse_all).
    `client`: an open client emptied and set up again instead (what a program simulating many
    scenes can do; benchmarks/speed_front.py times both)."""
    keep_freed_memory()
    if client is None:
        c = pb.connect(pb.DIRECT)
    else:
        c = client
        pb.resetSimulation(physicsClientId=c)
    pb.setGravity(*[float(g) for g in gravity], physicsClientId=c)
    ours = {"splitImpulsePenetrationThreshold": 0} if split_impulse_all else {}
    pb.setPhysicsEngineParameter(
        fixedTimeStep=time_step, numSolverIterations=int(solver_iterations),
        numSubSteps=0, restitutionVelocityThreshold=0, warmStartingFactor=0, useSplitImpulse=True,
        contactSlop=0, enableConeFriction=False, deterministicOverlappingPairs=True, physicsClientId=c, **ours)
    return c


def add_floor(c: int, z: float, friction: float, restitution: float, body: str = "box") -> int:
    """A static floor with its top face at height z; returns its body id. body "plane": Bullet's
    infinite plane, the flat floor of Kubric's set-up (floor.body)."""
    # A thick box with its top face at z rather than GEOM_PLANE: creating a plane body costs
    # ~15 ms a scene (more than simulating it), the box 0.3 ms, and the contacts agree.
    if body == "plane":
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        floor = pb.createMultiBody(0, plane, basePosition=[0, 0, z], useMaximalCoordinates=True, physicsClientId=c)
    else:
        box = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[FLOOR_HALF_WIDTH, FLOOR_HALF_WIDTH, 1.0], physicsClientId=c)
        floor = pb.createMultiBody(0, box, basePosition=[0, 0, z - 1.0], useMaximalCoordinates=True, physicsClientId=c)
    pb.changeDynamics(floor, -1, lateralFriction=float(friction), restitution=float(restitution),
                      contactProcessingThreshold=0, physicsClientId=c)
    return floor


def build_world(spec: SceneSpec, cfg: dict, client: int | None = None) -> tuple[int, list[int]]:
    """A new DIRECT client (or `client`, emptied) holding the floor and the scene's objects.
    Returns (client, body ids)."""
    ph, fl = cfg["physics"], cfg["floor"]
    c = new_world(ph["gravity"], 1.0 / float(ph["rate"]), ph["solver_iterations"], ph.get("split_impulse_all", True),
                  client)
    if fl["enabled"]:
        add_floor(c, 0.0, fl["friction"], fl["restitution"], fl.get("body", "box"))
    bodies = []
    for o in spec.objects:
        shape = get_shape(o.shape)
        col = pb.createCollisionShape(pb.GEOM_MESH, vertices=(shape.vertices * o.scale).tolist(), physicsClientId=c)
        b = pb.createMultiBody(o.mass, col, basePosition=o.position.tolist(),
                               baseOrientation=xyzw(o.quaternion).tolist(), useMaximalCoordinates=True, physicsClientId=c)
        pb.changeDynamics(b, -1, lateralFriction=o.friction, restitution=o.restitution,
                          mass=o.mass, localInertiaDiagonal=o.inertia.tolist(), linearDamping=0, angularDamping=0,
                          contactProcessingThreshold=0, physicsClientId=c)
        if ph["ccd"]:
            # Continuous collision: a swept sphere inside the object stops it passing through
            # the floor within one step, at the price of slower contact handling.
            pb.changeDynamics(b, -1, ccdSweptSphereRadius=0.25 * o.scale, physicsClientId=c)
        pb.resetBaseVelocity(b, o.velocity.tolist(), o.angular_velocity.tolist(), physicsClientId=c)
        bodies.append(b)
    return c, bodies


def steps_per_frame(cfg: dict) -> int:
    return int(round(float(cfg["physics"]["rate"]) / float(cfg["scene"]["frame_rate"])))


def simulate(spec: SceneSpec, cfg: dict, after_frame=None, client: int | None = None) -> Scene:
    """Simulate one scene and record `scene.frames` frames (frame 0 is the initial state).
    `after_frame(t, client, bodies)`, if given, is called once each frame is recorded: a study may
    change the world there (pipelines/movi_a_sensitivity.py perturbs the state at one frame).
    `client`: an open client to reuse (emptied first, left open), else a fresh one, closed after."""
    frames, sub = int(cfg["scene"]["frames"]), steps_per_frame(cfg)
    n = len(spec.objects)
    pos = np.empty((frames, n, 3))
    quat = np.empty((frames, n, 4))
    vel = np.empty((frames, n, 3))
    ang = np.empty((frames, n, 3))
    c, bodies = build_world(spec, cfg, client)
    try:
        for t in range(frames):
            if t:
                for _ in range(sub):
                    pb.stepSimulation(physicsClientId=c)
            for j, b in enumerate(bodies):
                p, q = pb.getBasePositionAndOrientation(b, physicsClientId=c)
                v, w = pb.getBaseVelocity(b, physicsClientId=c)
                pos[t, j], quat[t, j], vel[t, j], ang[t, j] = p, wxyz(q), v, w
            if after_frame is not None:
                after_frame(t, c, bodies)
    finally:
        if client is None:
            pb.disconnect(c)
    return Scene(
        positions=pos, quaternions=continuous(quat), velocities=vel, angular_velocities=ang,
        shape=[o.shape for o in spec.objects], material=[o.material for o in spec.objects],
        scale=np.array([o.scale for o in spec.objects]), mass=np.array([o.mass for o in spec.objects]),
        friction=np.array([o.friction for o in spec.objects]),
        restitution=np.array([o.restitution for o in spec.objects]),
        attrs={"scene_id": spec.scene_id, "seed": spec.seed, "index": spec.index,
               "size": ",".join(o.size for o in spec.objects)},
    )


# A recorded frame can catch an impact between the physics step that crossed the floor and the
# one that resolves it, so a vertex may legitimately sit one physics step of travel below the
# floor, or a few % of the size in a resting contact. Deeper than both is a bug or tunnelling.
MAX_SINK_FRACTION = 0.05


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., V, 3) by unit quaternions q (..., 4) in w x y z order."""
    w, u = q[..., None, :1], q[..., None, 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def floor_violations(sc: Scene, meshes: dict, floor_z: float, physics_dt: float) -> list[tuple[int, int, float]]:
    """(object, first bad frame, depth) for objects sunk deeper than contact can explain.

    Between two physics steps a vertex can travel (|v| + |w| r) dt into the floor before the
    solver reacts; a recorded frame may hold that depth, or the frame after it (when the
    bounce has already slowed the object), so the bound uses the faster of the two frames.
    """
    out = []
    for n, name in enumerate(sc.shape):
        rest = sc.scale[n] * meshes[name][0]
        verts = rotate(sc.quaternions[:, n], rest[None])
        sink = floor_z - (verts[..., 2] + sc.positions[:, n, 2:3]).min(axis=-1)
        reach = np.linalg.norm(rest, axis=-1).max()
        speed = np.linalg.norm(sc.velocities[:, n], axis=-1) + np.linalg.norm(sc.angular_velocities[:, n], axis=-1) * reach
        speed[1:] = np.maximum(speed[1:], speed[:-1])
        bad = sink > np.maximum(MAX_SINK_FRACTION * sc.scale[n], 2.0 * speed * physics_dt)
        if bad.any():
            t = int(np.argmax(bad))
            out.append((n, t, float(sink[t])))
    return out


# The dataset: each shard simulated in memory by whichever process takes it, and written in place
# (the plan and the folder's claim are datagen/output.py's).


def _meshes(cfg: dict) -> dict:
    return {name: (get_shape(name).vertices, get_shape(name).faces) for name in cfg["scene"]["shapes"]}


def build_task(task: ShardTask, cfg: dict, seed: int) -> tuple[bytes, list[str]]:
    """Simulate one shard in memory. Returns the shard file's bytes and ids of tunnelled scenes."""
    scenes = [simulate(sample_scene(cfg, seed, task.split, i), cfg) for i in range(task.first, task.first + task.count)]
    meshes = _meshes(cfg)
    floor = cfg["floor"]["enabled"]
    dt = 1.0 / float(cfg["physics"]["rate"])
    if floor:
        for sc in scenes:
            for n, t in off_floor(sc)[:1]:
                # the floor is declared everywhere: an object past its edge would fall through it
                raise DataError(f"scene {sc.attrs['scene_id']}: object {n} left the physics floor (|x| or |y| above "
                                f"{FLOOR_HALF_WIDTH:g}) at frame {t}; slow the tosses or shrink the spawn box")
    bad = [sc.attrs["scene_id"] for sc in scenes if floor and floor_violations(sc, meshes, 0.0, dt)]
    image = shard_image(scenes, meshes, {"split": task.split, "shard": task.shard, "seed": seed,
                                         "first_scene": task.first}, task.name)
    return image, bad


def run_task(args) -> tuple[str, int, list[str]]:
    """Simulate and write one shard. Returns its name, scene count and ids of tunnelled scenes."""
    task, cfg, seed, out, planned = args
    try:
        image, bad = build_task(task, cfg, seed)
    except OSError as e:  # HDF5 failing to build the file in memory: one line, as a failed write
        raise write_error(Path(out) / task.name, e) from None
    commit_shard(Path(out), planned, task.name, image)
    return task.name, task.count, bad


def metadata(cfg: dict, seed: int, counts: dict[str, int], tasks: list[ShardTask], complete: bool) -> dict:
    sc = cfg["scene"]
    materials = [cfg["materials"][m] for m in sc["materials"]]
    vary = len({(m["friction"], m["restitution"]) for m in materials}) > 1
    return {
        "complete": complete,
        "generator": "datagen toss",
        "generator_version": __version__,
        "seed": seed,
        "config": cfg,
        "frame_rate": float(sc["frame_rate"]),
        "physics_rate": float(cfg["physics"]["rate"]),
        "steps_per_frame": steps_per_frame(cfg),
        "num_frames": int(sc["frames"]),
        "gravity": [float(g) for g in cfg["physics"]["gravity"]],
        "floor": ({"z": 0.0, "friction": float(cfg["floor"]["friction"]),
                   "restitution": float(cfg["floor"]["restitution"])} if cfg["floor"]["enabled"] else None),
        "materials_vary": vary,
        "quaternion_order": "wxyz",
        "shapes": {n: {"num_vertices": int(len(get_shape(n).vertices)), "num_faces": int(len(get_shape(n).faces))}
                   for n in sc["shapes"]},
        "splits": {s: {"num_scenes": counts.get(s, 0), "shards": [t.name for t in tasks if t.split == s]}
                   for s in SPLITS},
    }


BACKENDS = ("process", "ray")


def _check_arguments(counts: dict[str, int], workers: int, per_shard: int, backend: str,
                     ray_address: str | None = None) -> None:
    """Refuse bad counts, sizes or backend before anything is written."""
    for split, n in counts.items():
        if n < 0:
            raise DataError(f"scene count for {split} must be >= 0, got {n}")
    if sum(counts.values()) < 1:
        raise DataError("nothing to generate: give at least one scene")
    if workers < 1:
        raise DataError(f"--workers must be >= 1, got {workers}")
    if per_shard < 1:
        raise DataError(f"--scenes-per-shard must be >= 1, got {per_shard}")
    if backend not in BACKENDS:
        raise DataError(f"unknown backend {backend!r}; use {' or '.join(BACKENDS)}")
    if ray_address and backend != "ray":
        raise DataError("--ray-address needs --backend ray (the process backend runs on this machine only)")
    if backend == "ray":
        from .ray_backend import require_ray
        require_ray()


def _shard_results(todo: list[ShardTask], cfg: dict, seed: int, out: Path, workers: int, ray, planned: dict):
    """Write the shards of `todo` on the chosen backend, yielding (name, count, tunnelled ids) for each."""
    jobs = [(t, cfg, seed, str(out), planned) for t in todo]
    if ray is not None and todo:
        from .ray_backend import ray_tasks
        yield from ray_tasks(ray, todo, cfg, seed, out, planned)
    elif workers == 1 or len(todo) <= 1:
        for job in jobs:
            yield run_task(job)
    else:
        # fork where the platform has it: a spawned worker pays ~0.5 s re-importing trimesh and
        # h5py, a fifth of a small run. Safe while the parent holds no PyBullet client and no
        # native threads; once torch or Ray has started theirs (a pipeline, a test run) a forked
        # child can inherit a lock held by one of them and hang, so workers then come from a
        # clean fork server
        threaded = "torch" in sys.modules or "ray" in sys.modules
        methods = mp.get_all_start_methods()
        method = ("forkserver" if threaded and "forkserver" in methods else "fork") if "fork" in methods else "spawn"
        with mp.get_context(method).Pool(min(workers, len(todo)), initializer=leave_signals_to_parent) as pool:
            yield from pool.imap_unordered(run_task, jobs)


def _make_shards(mine: list[ShardTask], todo: list[ShardTask], cfg: dict, seed: int, out: Path, workers: int,
                 ray, planned: dict, progress: bool) -> list[str]:
    """Write the missing shards under a progress bar counting all of this run's scenes; returns
    the ids of tunnelled scenes."""
    total = sum(t.count for t in mine)
    bar = tqdm(total=total, initial=total - sum(t.count for t in todo),
               unit="scene", desc="toss", disable=not progress, file=sys.stderr)
    tunnelled: list[str] = []
    for _, n, bad in _shard_results(todo, cfg, seed, out, workers, ray, planned):
        bar.update(n)
        tunnelled += bad
    bar.close()
    return tunnelled


def _warn_tunnelled(tunnelled: list[str]) -> None:
    if tunnelled:
        # Kept, not dropped, so the dataset stays a function of the seed; inspect lists them.
        print(f"warning: {len(tunnelled)} scene(s) sank through the floor (objects too fast for "
              f"physics.rate; set physics.ccd=true or raise the rate): {', '.join(sorted(tunnelled)[:10])}",
              file=sys.stderr)


def generate(cfg: dict, seed: int, counts: dict[str, int], out: str | Path, workers: int = 1,
             per_shard: int = 50, resume: bool = False, overwrite: bool = False, progress: bool = True,
             backend: str = "process", shard_index: int | None = None, num_shards: int | None = None,
             ray_address: str | None = None) -> dict:
    """Generate a dataset into `out`, or, with `num_shards`, the part `shard_index` of it: the
    shards whose position in the plan (train, then valid, then test shards, each in order)
    modulo num_shards is shard_index. Returns the metadata written last; its `complete` is
    false when other parts are still missing."""
    out = Path(out)
    _check_arguments(counts, workers, per_shard, backend, ray_address)
    sharded = num_shards is not None or shard_index is not None
    if sharded:
        from .shared_output import check_sharding
        check_sharding(shard_index, num_shards, overwrite)
    check_floor_covers(cfg)
    tasks = plan(counts, per_shard)
    meta = metadata(cfg, seed, counts, tasks, complete=False)
    mine = [t for k, t in enumerate(tasks) if not sharded or k % num_shards == shard_index]
    check_output(out, meta, sharded, resume, overwrite)     # fails fast, before a cluster is asked
    if backend == "ray":
        from .ray_backend import ray_cluster
    with (ray_cluster(workers, ray_address) if backend == "ray" else nullcontext()) as ray:
        try:
            with claim(out, shared=sharded):
                # A part skips its shards already written (and verified), so a requeued array
                # task redoes only what is missing; a whole run does so only with --resume.
                todo = start_output(out, meta, mine, sharded, resume, overwrite)
                with temporaries_removed_on_failure(out, [t.name for t in todo], whole_run=not sharded):
                    tunnelled = _make_shards(mine, todo, cfg, seed, out, workers, ray, plan_of(meta), progress)
                _warn_tunnelled(tunnelled)
                return finalise(out, meta, tasks)
        except Busy:
            from .shared_output import busy_error
            raise busy_error(out, meta, sharded) from None
