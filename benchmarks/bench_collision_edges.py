"""Cost of building collision edges: grows with contacts, not with the square of the vertex count.

For scenes of N MOVi-A spheres (62 vertices each), laid out either apart (a grid, no two
within the radius) or touching in a row (each neighbour pair in contact), times
gns.contacts.collision_edges (broad phase on object bounds, then only vertices near a contact)
against the brute force (all vertex pairs of different objects, one cdist), both in the same
run, and checks that both find the same edges. The last columns time vertex-to-surface edges
(gns.contacts, `features.collision_mode = "surface"`) on the same scenes.

    python benchmarks/bench_collision_edges.py [--objects 3,10,30,100]
"""
from __future__ import annotations

import argparse
import time

import torch

from datagen.scenes import get_shape
from gns.contacts import surface_edges
from gns.contacts import collision_edges
from gns.graph import MeshLibrary

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
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    header = (f"{'objects':>8}{'vertices':>10}{'layout':>10}{'edges':>8}{'ours ms':>10}{'brute ms':>10}{'brute/ours':>12}"
              f"{'surface edges':>15}{'surface ms':>12}")
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
            row = {"objects": n, "vertices": graph.num_nodes, "layout": "touching" if touching else "apart",
                   "edges": len(ours.senders), "ours_ms": t_ours, "brute_ms": t_brute,
                   "surface_edges": len(surface_edges(x, graph, RADIUS).senders), "surface_ms": t_surface}
            rows.append(row)
            print(f"{n:>8}{graph.num_nodes:>10}{row['layout']:>10}{row['edges']:>8}{t_ours:>10.2f}{t_brute:>10.2f}"
                  f"{t_brute / t_ours:>11.1f}x{row['surface_edges']:>15}{t_surface:>12.2f}")
    print(f"\nradius {RADIUS}; best of {a.repeats}; 1 thread; edges identical to the brute force in every row")
    return rows


if __name__ == "__main__":
    main()
