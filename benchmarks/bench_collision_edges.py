"""Cost of building collision edges: grows with contacts, not with the square of the vertex count.

For scenes of N MOVi-A spheres (62 vertices each), laid out either apart (a grid, no two
within the radius) or touching in a row (each neighbour pair in contact), times
gns.contacts.collision_edges (broad phase on object bounds, then only vertices near a contact)
against the brute force (all vertex pairs of different objects, one cdist), both in the same
run, and checks that both find the same edges. The last columns time vertex-to-surface edges
(gns.contacts, `features.collision_mode = "surface"`) and face-face edges (gns.face_contacts,
`"face"`) on the same scenes.

With --data DIR (a dataset of several objects a scene, e.g. `datagen toss --objects 3-10`), every
recorded frame of its test scenes instead: per number of objects, the object pairs in contact
(closer than the radius), the edges each mode builds and its build time per frame, all modes on
the same frames; and how many of the pairs in contact each mode sees (some edge joins them). Then
the impacts: pairs touching (closer than 0.02) at a frame but not at the one before, and how many
of them face edges of the frame before already joined, built at x_t and where the vertices go at
constant velocity (2 x_t - x_t-1): how many impacts a model's edges cannot see coming.

    python benchmarks/bench_collision_edges.py [--objects 3,10,30,100]
    python benchmarks/bench_collision_edges.py --data data/multi_test [--radius 0.25] [--limit 100]
"""
from __future__ import annotations

import argparse
import time

import torch

from datagen.scenes import get_shape
from gns.contacts import collision_edges, surface_edges
from gns.face_contacts import face_edges
from gns.graph import MeshLibrary

MODES = {"vertex": collision_edges, "surface": surface_edges, "face": face_edges}

RADIUS = 0.15


def scene(n: int, touching: bool):
    sphere = get_shape("sphere")
    lib = MeshLibrary({"sphere": (sphere.vertices, sphere.faces)})
    graph = lib.pack(lib.shape_ids(["sphere"] * n), torch.ones(n, dtype=torch.float64), torch.full((n,), 0.5),
                     torch.full((n,), 0.5), torch.zeros(n, dtype=torch.int64))
    if touching:  # a row of unit spheres whose surfaces nearly touch
        centres = torch.stack([torch.arange(n, dtype=torch.float64) * 1.02, torch.zeros(n), torch.zeros(n)], 1)
    else:
        side = int(n ** 0.5) + 1
        k = torch.arange(n)
        centres = torch.stack([(k % side) * 3.0, (k // side) * 3.0, torch.zeros(n)], 1).to(torch.float64)
    return graph, graph.rest + centres[graph.node_graph]


def brute_force(x, graph, radius):
    d = torch.cdist(x, x)
    other = graph.node_graph[:, None] != graph.node_graph[None, :]
    s, r = torch.nonzero((d < radius) & other, as_tuple=True)
    return s, r


def best_ms(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--objects", default="3,10,30,100", help="comma list of object counts")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--data", help="a dataset of several objects a scene: time every mode on its test frames")
    ap.add_argument("--radius", type=float, default=0.25, help="with --data: the collision radius (movi_a_multi's 0.25)")
    ap.add_argument("--limit", type=int, default=100, help="with --data: at most this many test scenes")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.data:
        return on_dataset(a.data, a.radius, a.limit)
    header = (f"{'objects':>8}{'vertices':>10}{'layout':>10}{'edges':>8}{'ours ms':>10}{'brute ms':>10}{'brute/ours':>12}"
              f"{'surface edges':>15}{'surface ms':>12}{'face edges':>12}{'face ms':>10}")
    print(header)
    print("-" * len(header))
    rows = []
    for n in [int(v) for v in a.objects.split(",")]:
        for touching in (False, True):
            graph, x = scene(n, touching)
            ours = collision_edges(x, graph, RADIUS)
            s, r = brute_force(x, graph, RADIUS)
            same = set(zip(ours.senders.tolist(), ours.receivers.tolist())) == set(zip(s.tolist(), r.tolist()))
            if not same:
                raise SystemExit(f"collision edges differ from the brute force at {n} objects")
            t_ours = best_ms(lambda: collision_edges(x, graph, RADIUS), a.repeats)
            t_brute = best_ms(lambda: brute_force(x, graph, RADIUS), a.repeats)
            t_surface = best_ms(lambda: surface_edges(x, graph, RADIUS), a.repeats)
            t_face = best_ms(lambda: face_edges(x, graph, RADIUS), a.repeats)
            row = {"objects": n, "vertices": graph.num_nodes, "layout": "touching" if touching else "apart",
                   "edges": len(ours.senders), "ours_ms": t_ours, "brute_ms": t_brute,
                   "surface_edges": len(surface_edges(x, graph, RADIUS).senders), "surface_ms": t_surface,
                   "face_edges": len(face_edges(x, graph, RADIUS).senders), "face_ms": t_face}
            rows.append(row)
            print(f"{n:>8}{graph.num_nodes:>10}{row['layout']:>10}{row['edges']:>8}{t_ours:>10.2f}{t_brute:>10.2f}"
                  f"{t_brute / t_ours:>11.1f}x{row['surface_edges']:>15}{t_surface:>12.2f}"
                  f"{row['face_edges']:>12}{t_face:>10.2f}")
    print(f"\nradius {RADIUS}; best of {a.repeats}; 1 thread; edges identical to the brute force in every row")
    return rows


def joined_pairs(e, graph) -> set[tuple[int, int]]:
    """Object pairs (a < b) some edge of e joins."""
    a, b = graph.node_graph[e.senders], graph.node_graph[e.receivers]
    return {(int(min(i, j)), int(max(i, j))) for i, j in zip(a, b)}


def on_dataset(data: str, radius: float, limit: int) -> list[dict]:
    from datagen.shards import Dataset
    from gns.data import vertices_from_poses
    from datagen.shards import rotation
    ds = Dataset(data)
    lib = MeshLibrary(ds.meshes)
    scenes = ds.load("test")[:limit]
    totals: dict[int, dict] = {}
    impacts = {"impacts": 0, "seen_now": 0, "seen_ahead": 0}
    for sc in scenes:
        n = sc.num_objects
        graph = lib.pack(lib.shape_ids(sc.shape), torch.from_numpy(sc.scale), torch.from_numpy(sc.friction),
                         torch.from_numpy(sc.restitution), torch.zeros(n, dtype=torch.int64))
        rot = torch.from_numpy(rotation(sc.quaternions.reshape(-1, 4)).as_matrix()).view(sc.num_frames, n, 3, 3)
        frames = vertices_from_poses(graph, torch.from_numpy(sc.positions).transpose(0, 1), rot.transpose(0, 1))
        t = totals.setdefault(n, {"frames": 0, "contacts": 0, **{f"{m}_{k}": 0.0 for m in MODES for k in ("edges", "ms", "seen")}})
        face_pairs = []
        for f in range(sc.num_frames):
            x = frames[:, f].contiguous()
            joined = {}
            for mode, build in MODES.items():
                start = time.perf_counter()
                e = build(x, graph, radius)
                t[f"{mode}_ms"] += (time.perf_counter() - start) * 1e3
                t[f"{mode}_edges"] += len(e.senders)
                joined[mode] = joined_pairs(e, graph)
            # the face mode joins every pair of triangles closer than the radius, by the exact
            # distance: its pairs are the pairs in contact, the reference for what the others see
            contact = joined["face"]
            face_pairs.append(contact)
            t["frames"] += 1
            t["contacts"] += len(contact)
            for mode in MODES:
                t[f"{mode}_seen"] += len(contact & joined[mode])
        count_impacts(frames, graph, radius, face_pairs, impacts)
    header = f"{'objects':>8}{'frames':>8}{'pairs in contact':>18}" + "".join(
        f"{mode + ' edges':>15}{'ms':>7}{'sees':>7}" for mode in MODES)
    print(f"{ds.root}: {len(scenes)} test scenes, every frame; radius {radius}; 1 thread; per frame")
    print(header)
    print("-" * len(header))
    rows = []
    for n in sorted(totals):
        t = totals[n]
        row = {"objects": n, "frames": t["frames"], "contacts_per_frame": t["contacts"] / t["frames"]}
        line = f"{n:>8}{t['frames']:>8}{row['contacts_per_frame']:>18.2f}"
        for mode in MODES:
            row[f"{mode}_edges"] = t[f"{mode}_edges"] / t["frames"]
            row[f"{mode}_ms"] = t[f"{mode}_ms"] / t["frames"]
            row[f"{mode}_sees"] = t[f"{mode}_seen"] / max(t["contacts"], 1)
            line += f"{row[f'{mode}_edges']:>15.1f}{row[f'{mode}_ms']:>7.2f}{row[f'{mode}_sees']:>6.0%} "
        rows.append(row)
        print(line)
    print("pairs in contact: object pairs closer than the radius (exact triangle distance); sees: the share of "
          "them some edge of the mode joins")
    k = max(impacts["impacts"], 1)
    print(f"impacts (pairs closer than {TOUCH} at a frame, not at the one before): {impacts['impacts']}; face edges "
          f"of the frame before join {impacts['seen_now'] / k:.0%} of them built at x_t, "
          f"{impacts['seen_ahead'] / k:.0%} built ahead (2 x_t - x_t-1)")
    return rows + [impacts]


TOUCH = 0.02


def count_impacts(frames: torch.Tensor, graph, radius: float, face_pairs: list[set], into: dict) -> None:
    """Adds a scene's impacts (frames (N, F, 3)) to `into`: pairs that touch at frame f and not at
    f - 1, and whether face edges at f - 1 join them, built at x_{f-1} (`face_pairs`, the pairs
    the timed face edges of each frame joined) and ahead of it."""
    touching = [joined_pairs(face_edges(frames[:, f].contiguous(), graph, TOUCH), graph)
                for f in range(frames.shape[1])]
    for f in range(2, frames.shape[1]):
        new = touching[f] - touching[f - 1]
        if not new:
            continue
        ahead = (2 * frames[:, f - 1] - frames[:, f - 2]).contiguous()
        seen_ahead = joined_pairs(face_edges(ahead, graph, radius), graph)
        into["impacts"] += len(new)
        into["seen_now"] += len(new & face_pairs[f - 1])
        into["seen_ahead"] += len(new & seen_ahead)


if __name__ == "__main__":
    main()
