"""Collision edges between the objects of a scene: vertex-vertex (`collision_edges`, the default)
and vertex-to-surface (`surface_edges`, `features.collision_mode = "surface"`).

Vertex-vertex edges (`collision_edges`) see a contact only when two *vertices* come
within the radius; on coarse meshes two surfaces touch long before that (docs/model.md). Here
each vertex of an object near another object is joined to that object's *surface*: the
closest point on its triangles. The edge goes from the triangle's vertex nearest that point
(a node, whose latent sends the message) to the query vertex, and carries the exact geometry:
d = x_vertex - closest point, and the signed distance (negative inside the other object,
whose faces are oriented outward from its vertex mean: the meshes are convex). As FIGNet's
face-face edges, it needs faces in the graph (`GraphBatch.faces`); unlike them it stays a vertex
graph. Every vertex of each near object pair queries the other object, so a contact gets
edges in both directions. Phases and cost as collision_edges: bounds of object pairs, then
only the vertices inside the other's expanded bounds, each against the other's faces.
"""
from __future__ import annotations

import torch

from dataclasses import replace

from gns import triangles
from gns.graph import EdgeSet, GraphBatch, graph_centres, per_graph, ragged_arange


def closest_point_on_triangle(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Closest points (M, 3) of triangles (a, b, c) to points p, all (M, 3): Ericson's
    Voronoi-region test (gns.triangles, on rows)."""
    return triangles.rows(triangles.closest_point_on_triangle(*(triangles.columns(v) for v in (p, a, b, c))))


def smallest_per_group(group: torch.Tensor, value: torch.Tensor, size: int | None = None) -> torch.Tensor:
    """Index of the smallest value in each group (groups in ascending order); of equal values the
    first, so that the choice does not depend on what else the arrays hold. `size`: the groups
    are exactly 0..size-1, each present (no sort at all). Two scatters a group, not two argsorts:
    a crowded batch's face edges reduce millions of candidates a step."""
    if size is None:
        _, slot = torch.unique(group, return_inverse=True)
        size = int(slot.max()) + 1 if len(slot) else 0
    else:
        slot = group
    value = torch.nan_to_num(value, nan=torch.inf)     # a NaN is no group's smallest
    low = torch.full((size,), torch.inf, dtype=value.dtype, device=value.device).scatter_reduce(0, slot, value, "amin")
    at = value == low[slot]
    index = torch.arange(len(group), device=group.device)
    return torch.full((size,), len(group), dtype=torch.int64, device=group.device).scatter_reduce(
        0, slot[at], index[at], "amin")


@torch.no_grad()
def _surface_edges(x: torch.Tensor, graph: GraphBatch, radius: float) -> tuple[EdgeSet, torch.Tensor, torch.Tensor]:
    """surface_edges, with the triangle (E, 3) and the sign (E, 1) of each edge."""
    none = torch.zeros(0, 3, dtype=torch.int64, device=x.device)
    empty = EdgeSet(torch.zeros(0, dtype=torch.int64, device=x.device), torch.zeros(0, dtype=torch.int64, device=x.device),
                    torch.zeros(0, 3, dtype=x.dtype, device=x.device), torch.zeros(0, 1, dtype=x.dtype, device=x.device))
    if graph.faces is None:
        raise ValueError("surface collision edges need the graph's faces")
    near = near_pairs(x, graph, radius)
    if near is None:
        return empty, none, empty.signed
    a, b, low, high = near
    face_graph = graph.node_graph[graph.faces[:, 0]]
    face_counts = torch.bincount(face_graph, minlength=graph.num_graphs)
    face_start = torch.cumsum(face_counts, 0) - face_counts
    centre = graph_centres(x, graph)
    own = torch.cat([a, b])
    other = torch.cat([b, a])
    pair, node = vertices_near(x, graph, own, other, low, high, radius)
    if len(node) == 0:
        return empty, none, empty.signed
    # every query vertex against every face of the other object
    query, k = ragged_arange(face_counts[other[pair]])
    face = face_start[other[pair[query]]] + k
    tri = graph.faces[face]
    q = x[node[query]]
    v0, v1, v2 = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    closest = closest_point_on_triangle(q, v0, v1, v2)
    dist = (q - closest).norm(dim=-1)
    best = smallest_per_group(query, dist)   # the nearest face of each query vertex
    normal = torch.linalg.cross(v1[best] - v0[best], v2[best] - v0[best])
    outward = ((v0[best] - centre[other[pair[query[best]]]]) * normal).sum(-1, keepdim=True)
    normal = normal * torch.where(outward < 0, -1.0, 1.0).to(x.dtype)
    d = q[best] - closest[best]
    signed = torch.where((d * normal).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(x.dtype) * dist[best, None]
    keep = signed[:, 0] < radius
    best, d, signed = best[keep], d[keep], signed[keep]
    tri = tri[best]
    corner = (x[tri] - closest[best][:, None]).norm(dim=-1).argmin(dim=1)
    sender = tri.gather(1, corner[:, None])[:, 0]
    return EdgeSet(sender, node[query[best]], d, signed), tri, torch.sign(signed)


def surface_edges(x: torch.Tensor, graph: GraphBatch, radius: float) -> EdgeSet:
    """Edges from the surface of one object to the vertices of another within `radius` of it
    (or inside it); `vectors` (E, 3) = x_r - closest point, `signed` (E, 1) signed distance.

    Which edges is decided without gradient; their geometry is computed again from x for the
    chosen triangles (the same numbers), so that a differentiable rollout's gradient flows
    through the contact features too."""
    edges, tri, sign = _surface_edges(x, graph, radius)
    if not (torch.is_grad_enabled() and x.requires_grad) or len(edges.senders) == 0:
        return edges
    q = x[edges.receivers]
    d = q - closest_point_on_triangle(q, x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]])
    return EdgeSet(edges.senders, edges.receivers, d, sign * d.norm(dim=-1, keepdim=True))


def candidate_pairs(graph: GraphBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """All unordered pairs (a < b) of graphs in the same scene: two (P,) int64 tensors."""
    scene = graph.graph_scene
    order = torch.argsort(scene, stable=True)
    _, counts = torch.unique_consecutive(scene[order], return_counts=True)
    # for the k-th graph of a scene (in `order`), pair it with every graph of its scene
    owner, _ = ragged_arange(counts)                     # scene run of each sorted graph
    run_start = torch.cumsum(counts, 0) - counts
    per = counts[owner]                                   # (G,) partners per sorted graph
    who, k = ragged_arange(per)
    a, b = order[who], order[run_start[owner[who]] + k]
    keep = a < b
    return a[keep], b[keep]


def ragged_take(counts: torch.Tensor, start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For blocks p of counts[p] consecutive indices from start[p]: (owner, index) of each element."""
    owner, local = ragged_arange(counts)
    return owner, start[owner] + local


def near_pairs(x: torch.Tensor, graph: GraphBatch, radius: float):
    """Broad phase: object pairs (a < b) of a scene whose bounds, one expanded by `radius`,
    overlap; returns (a, b, low, high) with every graph's bounds (G, 3), or None if none."""
    if graph.graph_scene is None or graph.num_graphs < 2:
        return None
    high, low = per_graph(x, graph, "amax"), per_graph(x, graph, "amin")
    a, b = candidate_pairs(graph)
    near = ((low[a] - high[b] <= radius) & (low[b] - high[a] <= radius)).all(dim=1)
    if not near.any():
        return None
    return a[near], b[near], low, high


def vertices_near(x: torch.Tensor, graph: GraphBatch, own: torch.Tensor, other: torch.Tensor, low: torch.Tensor,
                   high: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mid phase: the vertices of graphs `own` (P,) inside the bounds of `other` (P,) expanded
    by `radius`; returns (pair, node), pair indexing own/other."""
    counts = torch.bincount(graph.node_graph, minlength=graph.num_graphs)
    pair, node = ragged_take(counts[own], torch.cumsum(counts, 0)[own] - counts[own])
    p = x[node]
    ok = ((p >= low[other][pair] - radius) & (p <= high[other][pair] + radius)).all(dim=1)
    return pair[ok], node[ok]


@torch.no_grad()
def collision_edges(x: torch.Tensor, graph: GraphBatch, radius: float) -> EdgeSet:
    """Edges between vertices of different objects of the same scene closer than `radius`.

    x (N, 3) node positions at time t. Three phases, all vectorised (no Python loop):
    1. broad: object pairs of a scene whose axis-aligned bounds, one expanded by `radius`, overlap;
    2. mid: per such pair, only the vertices of each object inside the other's expanded bounds;
    3. narrow: distances of those vertex pairs, kept when < radius.
    The cost grows with the number of near object pairs and of vertices near a contact, not with
    the square of the vertex count. Both directions are returned (an edge and its reverse);
    objects alone in their scene (or a graph without `graph_scene`) get none.
    """
    empty = EdgeSet(torch.zeros(0, dtype=torch.int64, device=x.device),
                    torch.zeros(0, dtype=torch.int64, device=x.device))
    near = near_pairs(x, graph, radius)
    if near is None:
        return empty
    a, b, low, high = near

    def inside(own: torch.Tensor, other: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per pair, how many vertices of `own` are inside `other`'s expanded bounds, and which."""
        pair, node = vertices_near(x, graph, own, other, low, high, radius)
        return torch.bincount(pair, minlength=len(own)), node

    count_a, nodes_a = inside(a, b)
    count_b, nodes_b = inside(b, a)
    start_a = torch.cumsum(count_a, 0) - count_a
    start_b = torch.cumsum(count_b, 0) - count_b
    pair, local = ragged_arange(count_a * count_b)
    i = nodes_a[start_a[pair] + torch.div(local, count_b[pair], rounding_mode="floor")]
    j = nodes_b[start_b[pair] + local % count_b[pair]]
    close = (x[i] - x[j]).norm(dim=1) < radius
    i, j = i[close], j[close]
    return EdgeSet(torch.cat([i, j]), torch.cat([j, i]))


def with_collision_edges(graph: GraphBatch, x: torch.Tensor, radius: float) -> GraphBatch:
    """A copy of graph with its collision edges built from positions x (N, 3)."""
    return replace(graph, collision_edges=collision_edges(x, graph, radius))


def outward_normals(x: torch.Tensor, tri: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """Unit normals (F, 3) of triangles tri (F, 3) at positions x, outward from their object's
    centre (F, 3): the meshes are convex."""
    v0 = x[tri[:, 0]]
    normal = torch.linalg.cross(x[tri[:, 1]] - v0, x[tri[:, 2]] - v0)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp(min=torch.finfo(x.dtype).tiny)
    return normal * torch.where(((v0 - centre) * normal).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(x.dtype)


def _pushes(x: torch.Tensor, graph: GraphBatch, centre: torch.Tensor, reach: torch.Tensor, low: torch.Tensor,
            high: torch.Tensor, a: torch.Tensor, b: torch.Tensor):
    """Every vertex of objects a, b (P,) inside the other of its pair: (own, other, push) with push
    (M, 3) the shortest move of the vertex out of the other's convex hull, through the face whose
    plane it is least deep behind. Broad phase as collision_edges, then only the vertices within
    the other's bounding sphere (centre (G, 3), reach (G,)), each against the other's face planes:
    a dot product a face, no closest point (inside a convex mesh the nearest exit is a plane's).
    low, high (G, 3): every graph's bounds."""
    near = ((low[a] - high[b] <= 0) & (low[b] - high[a] <= 0)).all(dim=1)
    if not near.any():
        return None
    a, b = a[near], b[near]
    own, other = torch.cat([a, b]), torch.cat([b, a])
    pair, node = vertices_near(x, graph, own, other, low, high, 0.0)
    close = (x[node] - centre[other[pair]]).norm(dim=-1) < reach[other[pair]]
    pair, node = pair[close], node[close]
    if len(node) == 0:
        return None
    # the face planes of only the objects a vertex is inside the bounds of (a crowd's few pairs)
    tri = graph.faces
    face_counts = torch.bincount(graph.node_graph[tri[:, 0]], minlength=graph.num_graphs)
    face_start = torch.cumsum(face_counts, 0) - face_counts
    hosts, slot = torch.unique(other[pair], return_inverse=True)
    host, k = ragged_arange(face_counts[hosts])
    faces = tri[face_start[hosts][host] + k]
    normal = outward_normals(x, faces, centre[hosts][host])
    offset = (normal * x[faces[:, 0]]).sum(-1)
    host_start = torch.cumsum(face_counts[hosts], 0) - face_counts[hosts]
    query, k = ragged_arange(face_counts[hosts][slot])
    face = host_start[slot[query]] + k
    height = (normal[face] * x[node[query]]).sum(-1) - offset[face]   # < 0 behind the face's plane
    # the face of the largest height (the least deep plane) of each vertex: inside if below zero
    best = smallest_per_group(query, -height, size=len(node))
    best = best[height[best] < 0]
    if len(best) == 0:
        return None
    q, f = query[best], face[best]
    return own[pair[q]], other[pair[q]], normal[f] * (-height[best])[:, None]


@torch.no_grad()
def separation(x: torch.Tensor, graph: GraphBatch, floor_z: float | None = None, iterations: int = 8) -> torch.Tensor:
    """The translation (G, 3) of each object that takes the objects of a scene out of each other:
    the rollout option keep_apart, a projection after each step as shape matching is one.

    Per pair of objects, the deepest vertex of either inside the other is pushed out through the
    plane of the other's face it is least deep behind (`_pushes`: exact for convex meshes); the
    two objects share the push in inverse proportion to their bounding volume (heavier moves
    less: the graph holds no masses) and an object in several pairs averages its pushes (Jacobi,
    as position-based dynamics), a few iterations. No push takes an object below the floor.
    Objects that do not overlap are not moved at all. A scene none of whose objects moved in an
    iteration is done: the next would find the same pushes and move them no more, so it is left
    out of the rest (the same shifts to the bit; after the first iteration of a crowded batch only
    a scene or two still overlaps)."""
    shift = torch.zeros(graph.num_graphs, 3, dtype=x.dtype, device=x.device)
    if graph.faces is None or graph.graph_scene is None or graph.num_graphs < 2:
        return shift
    a, b = candidate_pairs(graph)
    centre = graph_centres(x, graph)
    reach = per_graph((x - centre[graph.node_graph]).norm(dim=-1), graph, "amax")
    volume = reach ** 3
    # The bounds and positions of the shifted objects, kept up to date for the objects that moved
    # only: a shift translates an object's bounds as they are (rounding is monotonic, so the same
    # to the bit as bounds of the shifted vertices), and after the first iteration few objects move.
    low0, high0 = per_graph(x, graph, "amin"), per_graph(x, graph, "amax")
    counts = torch.bincount(graph.node_graph, minlength=graph.num_graphs)
    starts = torch.cumsum(counts, 0) - counts
    y = x.clone()
    if floor_z is not None:
        room = (low0[:, 2] - floor_z).clamp(min=0)
    for _ in range(iterations):
        found = _pushes(y, graph, centre + shift, reach, low0 + shift, high0 + shift, a, b)
        if found is None:
            break
        own, other, push = found
        # one push per pair, its deepest vertex either way: the two ways can cancel (a cube's corner
        # at the other's centre sees three faces as near). As a push of the pair's first object:
        push = torch.where((own < other)[:, None], push, -push)
        own, other = torch.minimum(own, other), torch.maximum(own, other)
        best = smallest_per_group(own * graph.num_graphs + other, -push.norm(dim=-1))
        own, other, push = own[best], other[best], push[best] * (1 + 1e-6)
        w_own = (volume[other] / (volume[own] + volume[other]))[:, None]
        if floor_z is not None:
            # an object on the floor cannot go down: the other takes that push whole
            low = low0[:, 2] + shift[:, 2] - floor_z < 1e-9
            w_own = torch.where((low[own] & (push[:, 2] < 0))[:, None], 0.0, w_own)
            w_own = torch.where((low[other] & (push[:, 2] > 0))[:, None], 1.0, w_own)
        moved = torch.cat([own, other])
        step = torch.cat([w_own * push, -(1 - w_own) * push])
        total = torch.zeros_like(shift).index_add_(0, moved, step)
        count = torch.zeros(graph.num_graphs, dtype=x.dtype, device=x.device).index_add_(
            0, moved, torch.ones(len(moved), dtype=x.dtype, device=x.device))
        new = shift + total / count.clamp(min=1)[:, None]
        if floor_z is not None:
            # the floor does not give way: a push downwards stops where the lowest vertex meets it
            new[:, 2] = torch.maximum(new[:, 2], -room)
        changed = (new != shift).any(dim=1).nonzero()[:, 0]
        moving = torch.zeros(int(graph.graph_scene.max()) + 1, dtype=torch.bool, device=x.device)
        moving[graph.graph_scene[changed]] = True
        shift = new
        owner, nodes = ragged_take(counts[changed], starts[changed])
        y[nodes] = x[nodes] + shift[changed[owner]]
        live = moving[graph.graph_scene[a]]
        a, b = a[live], b[live]
        if len(a) == 0:
            break
    return shift
