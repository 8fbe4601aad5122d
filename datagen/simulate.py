"""The one place that sets up PyBullet: a world with its floor, a scene in it, stepped and recorded.

Settings follow Kubric's MOVi worker: a fresh client per scene (a reused world loses bit-exact
repeatability), contactProcessingThreshold=0 per body (without it bounces die), no restitution
velocity threshold, no warm starting, split impulse, no contact slop, deterministic overlapping
pairs, no damping, and the mesh's true inertia (Bullet would otherwise replace it with a box
approximation). baselines.pybullet builds its cube-toss worlds with `new_world` and `add_floor` too.
"""
from __future__ import annotations

import os
import sys

import numpy as np


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

from .scenes import SceneSpec, get_shape
from .shards import Scene, continuous, wxyz, xyzw


FLOOR_HALF_WIDTH = 1000.0


def check_floor_covers(cfg: dict) -> None:
    """Refuse a spawn box the physics floor (a box of half-width FLOOR_HALF_WIDTH) does not cover:
    the metadata declares a floor everywhere, so objects beyond its edge would fall through what
    the data calls a floor. (A wider box is no answer: contact precision falls with its size.)"""
    from .scenes import ConfigError
    if not cfg["floor"]["enabled"]:
        return
    sp = cfg["spawn"]
    reach = max(float(cfg["sizes"][n]) for n in cfg["scene"]["sizes"]) * max(
        float(np.linalg.norm(get_shape(n).vertices, axis=1).max()) for n in cfg["scene"]["shapes"])
    far = max(abs(float(v)) for corner in (sp["low"], sp["high"]) for v in corner[:2])
    if far + reach > FLOOR_HALF_WIDTH:
        raise ConfigError(f"spawn.low/high reach {far:g} from the origin, beyond the physics floor "
                          f"(|x|, |y| <= {FLOOR_HALF_WIDTH:g}); keep the spawn box within it or set floor.enabled=false")
    # Where a toss can fly in the scene's time, before anything is simulated: the start velocity is
    # u - x (u in the velocity box, towards the centre), and nothing but friction and collisions acts
    # sideways, so x + (u - x) t bounds the travel; it is linear in x, u and t, so corners suffice.
    t_end = float(cfg["scene"]["frames"]) / float(cfg["scene"]["frame_rate"])
    flown = max(abs(float(x) + (float(u) - float(x)) * t_end)
                for k in (0, 1) for x in (sp["low"][k], sp["high"][k])
                for u in (sp["velocity_low"][k], sp["velocity_high"][k]))
    if flown + reach > FLOOR_HALF_WIDTH:
        raise ConfigError(f"tosses from the spawn box can fly {flown:g} from the origin within the scene's "
                          f"{t_end:g} s, beyond the physics floor (|x|, |y| <= {FLOOR_HALF_WIDTH:g}); shrink the "
                          "spawn box or the velocity box, or shorten the scenes")


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


def step_only(spec: SceneSpec, cfg: dict) -> None:
    """Build and step the same world without recording: the benchmark's bare-PyBullet baseline."""
    frames, sub = int(cfg["scene"]["frames"]), steps_per_frame(cfg)
    c, _ = build_world(spec, cfg)
    try:
        for _ in range((frames - 1) * sub):
            pb.stepSimulation(physicsClientId=c)
    finally:
        pb.disconnect(c)


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
