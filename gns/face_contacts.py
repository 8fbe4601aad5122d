"""Face-face collision edges (`features.collision_mode = "face"`): FIGNet's contacts between the
triangles of two objects, carried by a vertex graph.

Vertex-to-surface edges (gns.contacts.surface_edges) see a contact only near a vertex: two coarse
meshes touching edge on edge, or a large face met by another object's edge in its middle, give
none until a vertex comes close. FIGNet (Allen et al., ICLR 2023) joins *faces*: for every pair of
triangles of two objects closer than the radius it takes the two closest points, p_r on the
receiving triangle and p_s on the sending one, and sends the contact to all three vertices of the
receiving triangle, so the corners of a large face hear of a contact in its middle.

Here each such face pair becomes an edge to each vertex v of the receiving triangle, from the
sending triangle's vertex nearest p_s (a node, whose latent sends the message), with the vectors
[p_r - p_s, v - p_r] and the signed distance |p_r - p_s| (negative when p_r lies behind the
sending face; 0 where the triangles cross, as in FIGNet: how deep objects overlap is the
business of the keep_apart projection, not of these edges). A contact on a mesh edge is as near
to both triangles that share it, so which pair wins is rounding's choice; these features are the same for either (a face normal, which is not,
is left out: d is along the normal wherever one is defined). Of the face pairs that reach a vertex
from one other object only the closest is kept, so a vertex has at most one edge from each object
and the edge count stays that of the vertices near contacts, as with surface edges.

Phases: object pairs whose bounds, one expanded by the radius, overlap (gns.contacts.near_pairs);
per pair, the triangles of each inside the other's expanded bounds and within the radius of the
sphere around the other's vertices; per pair, every such triangle
of one against every such triangle of the other whose expanded boxes overlap and neither of which
lies wholly beyond the radius on one side of the other's plane; then the exact
triangle-triangle distance (the 6 vertex-triangle and 9 edge-edge closest points, and where an
edge passes through the other triangle). Which edges is decided without gradient and in float32
(each scene at its own origin); the geometry is computed again from x for the chosen triangles, so a
differentiable rollout's gradient flows through the contact features too.
"""
from __future__ import annotations

import functools

import torch

from gns import triangles
from gns.contacts import closest_point_on_triangle, near_pairs, outward_normals, smallest_per_group
from gns.graph import EdgeSet, GraphBatch, graph_centres, per_graph, ragged_arange

VECTORS = 6   # the width of a face edge's vectors: p_r - p_s, v - p_r
CHUNK = 1 << 16   # triangle pairs measured at once: ~100 MB of temporaries


def _closest_stacked(s1: torch.Tensor, s2: torch.Tensor, compiled: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    on_1, on_2 = triangles.closest_points_on_triangles(triangles.vertices(s1), triangles.vertices(s2), compiled)
    return triangles.rows(on_1), triangles.rows(on_2)


def _distance_stacked(s1: torch.Tensor, s2: torch.Tensor, compiled: bool = False) -> torch.Tensor:
    return triangles.triangle_distance(triangles.vertices(s1), triangles.vertices(s2), compiled)


def closest_points_on_triangles(t1: torch.Tensor, t2: torch.Tensor, compiled: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest points (M, 3) on triangles t1 and t2 (M, 3, 3): the nearest of each vertex against
    the other triangle and each edge against each edge; triangles that cross, where an edge of one
    passes through the other, meet there (distance 0). `compiled`: through compiled code."""
    if compiled:
        return _compiled(_closest_stacked)(triangles.stacked(t1), triangles.stacked(t2), True)
    return _closest_stacked(triangles.stacked(t1), triangles.stacked(t2))


def _distance(t1: torch.Tensor, t2: torch.Tensor) -> torch.Tensor:
    """The distance between triangles t1 and t2 (M, 3, 3), without their closest points."""
    return _distance_stacked(triangles.stacked(t1), triangles.stacked(t2))


@functools.cache
def _compiled(fn):
    """fn through torch.compile (dynamic shapes): its elementwise work fused, equal to fn to
    rounding. It compiles at its first call (tens of seconds), once a process. On a CPU
    without the C++ compiler inductor needs, fn itself (gns.speedups.compiled warns of it for
    the network)."""
    from gns.speedups import cpp_compiler
    return torch.compile(fn, dynamic=True) if cpp_compiler() else fn


def compiled_distance():
    """_distance compiled: ~6x faster on a CPU (experiments/log.md). The columns are made
    contiguous before the compiled code is entered, which reads them 4x faster so."""
    measure = _compiled(_distance_stacked)
    return lambda t1, t2: measure(triangles.stacked(t1), triangles.stacked(t2), True)


def _beyond_plane(t1: torch.Tensor, t2: torch.Tensor, radius: float) -> torch.Tensor:
    """Whether all of triangle t2 lies farther than radius on one side of the plane of t1 (M,):
    then no point of t2 comes within radius of t1. A degenerate t1 (no plane) rules nothing out."""
    u, v = t1[:, 1] - t1[:, 0], t1[:, 2] - t1[:, 0]
    n = torch.linalg.cross(u, v)
    height = ((t2 - t1[:, :1]) * n[:, None]).sum(-1)            # (M, 3), in units of |n|
    size = n.norm(dim=-1)
    reach = radius * size[:, None]
    # a sliver's normal is rounding's direction, not one its triangle lies across
    flat = size <= max(1e-9, 100 * torch.finfo(t1.dtype).eps) * u.norm(dim=-1) * v.norm(dim=-1)
    return ~flat & ((height > reach).all(1) | (height < -reach).all(1))


def _plausible(tri: torch.Tensor, face_low: torch.Tensor, face_high: torch.Tensor, fa: torch.Tensor,
               fb: torch.Tensor, radius: float) -> torch.Tensor:
    """Whether face pairs (fa, fb) of triangles tri (F, 3, 3) may come within radius (M,): their
    boxes (F, 3) expanded by radius meet, and neither triangle lies wholly beyond the radius of
    the other's plane (that rules out a third of the pairs whose boxes meet, at a fraction of the
    exact test's cost)."""
    boxes = ((face_low[fa] <= face_high[fb] + radius) & (face_low[fb] <= face_high[fa] + radius)).all(dim=1)
    t1, t2 = tri[fa], tri[fb]
    return boxes & ~(_beyond_plane(t1, t2, radius) | _beyond_plane(t2, t1, radius))


def _faces_near(graph: GraphBatch, own: torch.Tensor, other: torch.Tensor, low: torch.Tensor,
                high: torch.Tensor, radius: float, tri: torch.Tensor, face_low: torch.Tensor,
                face_high: torch.Tensor, centre: torch.Tensor, reach: torch.Tensor):
    """Per directed pair p (own[p], other[p]): the faces of own whose boxes meet other's bounds
    expanded by radius and which come within radius of the sphere (centre (G, 3), reach (G,))
    around other's vertices. Returns (counts (P,), faces (F',)) with each pair's faces consecutive.

    The sphere keeps a face only if it can reach the other object at all: a box holds the faces
    of its corners too, and of a round or tilted object those are far; with the sphere the pairs
    of faces to test are 2.5x fewer in crowded MOVi-A scenes (experiments/log.md)."""
    face_graph = graph.node_graph.index_select(0, graph.faces[:, 0])
    face_counts = torch.bincount(face_graph, minlength=graph.num_graphs)
    face_start = torch.cumsum(face_counts, 0) - face_counts
    pair, k = ragged_arange(face_counts[own])
    face = face_start[own[pair]] + k
    ok = ((face_low[face] <= high[other][pair] + radius) & (face_high[face] >= low[other][pair] - radius)).all(dim=1)
    pair, face = pair[ok], face[ok]
    q = centre[other[pair]].to(tri.dtype)
    t = tri[face]
    near = closest_point_on_triangle(q, t[:, 0], t[:, 1], t[:, 2])
    ok = (near - q).norm(dim=-1) < reach[other[pair]] + radius
    return torch.bincount(pair[ok], minlength=len(own)), face[ok]


def _geometry(x: torch.Tensor, graph: GraphBatch, receiving: torch.Tensor, sending: torch.Tensor,
              corner: torch.Tensor, compiled: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The vectors (E, 6), signed distances (E, 1) and sending points p_s (E, 3) of edges to
    vertex `corner` (0-2) of face `receiving` from face `sending`, from positions x."""
    tri_r, tri_s = graph.faces[receiving], graph.faces[sending]
    p_r, p_s = closest_points_on_triangles(x[tri_r], x[tri_s], compiled)
    normal = outward_normals(x, tri_s, graph_centres(x, graph)[graph.node_graph[tri_s[:, 0]]])
    d = p_r - p_s
    v = x[tri_r.gather(1, corner[:, None])[:, 0]]
    inside = (d * normal).sum(-1, keepdim=True) < 0
    signed = torch.where(inside, -1.0, 1.0).to(x.dtype) * d.norm(dim=-1, keepdim=True)
    return torch.cat([d, v - p_r], -1), signed, p_s


def _closest_per_vertex(fa: torch.Tensor, fb: torch.Tensor, dist: torch.Tensor, graph: GraphBatch):
    """Of face pairs (fa, fb) with distances dist, per receiving vertex and sending object the
    closest (receiving face, sending face, corner): first the closest sending face per receiving
    face and object, then the closest of a vertex's faces (the same choice as taking the closest
    over all six corner-and-direction copies of every pair at once, at a third of the sorting)."""
    receiving, sending, dist = torch.cat([fa, fb]), torch.cat([fb, fa]), torch.cat([dist, dist])
    sender_graph = graph.node_graph[graph.faces[sending, 0]]
    best = smallest_per_group(receiving * graph.num_graphs + sender_graph, dist)
    receiving, sending, dist, sender_graph = receiving[best], sending[best], dist[best], sender_graph[best]
    corner = torch.arange(3, device=fa.device).repeat(len(receiving))
    receiving, sending, dist, sender_graph = (t.repeat_interleave(3) for t in (receiving, sending, dist, sender_graph))
    best = smallest_per_group(graph.faces[receiving, corner] * graph.num_graphs + sender_graph, dist)
    return receiving[best], sending[best], corner[best]


@torch.no_grad()
def _face_edges(x: torch.Tensor, graph: GraphBatch, radius: float, compiled: bool = False):
    """face_edges, with each edge's receiving face, sending face and receiving corner."""
    idx = torch.zeros(0, dtype=torch.int64, device=x.device)
    empty = EdgeSet(idx, idx, torch.zeros(0, VECTORS, dtype=x.dtype, device=x.device),
                    torch.zeros(0, 1, dtype=x.dtype, device=x.device))
    if graph.faces is None:
        raise ValueError("face collision edges need the graph's faces")
    if graph.graph_scene is None or graph.num_graphs < 2:
        return empty, idx, idx, idx
    # Which face pairs are near is decided in float32: half the memory traffic of every gather and
    # test of the millions of candidate pairs of a crowded batch. Each scene is taken to its own
    # origin first, so that rounding stays at 1e-7 of the scene's extent wherever the scene is,
    # which changes only near-ties (module doc). The edges' geometry is then computed from x itself.
    centre = graph_centres(x, graph)
    scenes = int(graph.graph_scene.max()) + 1
    origin = torch.zeros(scenes, 3, dtype=x.dtype, device=x.device).index_add_(0, graph.graph_scene, centre)
    origin = origin / torch.bincount(graph.graph_scene, minlength=scenes).clamp(min=1)[:, None].to(x.dtype)
    centre = centre - origin[graph.graph_scene]
    xs = x - origin[graph.graph_scene[graph.node_graph]]
    near = near_pairs(xs, graph, radius)
    if near is None:
        return empty, idx, idx, idx
    a, b, low, high = near
    tri = xs.to(torch.float32)[graph.faces]
    face_low, face_high = tri.amin(dim=1), tri.amax(dim=1)
    reach = per_graph((xs - centre[graph.node_graph]).norm(dim=-1), graph, "amax")
    count_a, faces_a = _faces_near(graph, a, b, low, high, radius, tri, face_low, face_high, centre, reach)
    count_b, faces_b = _faces_near(graph, b, a, low, high, radius, tri, face_low, face_high, centre, reach)
    start_a, start_b = torch.cumsum(count_a, 0) - count_a, torch.cumsum(count_b, 0) - count_b
    pair, local = ragged_arange(count_a * count_b)
    if len(pair) == 0:
        return empty, idx, idx, idx
    fa = faces_a[start_a[pair] + torch.div(local, count_b[pair], rounding_mode="floor")]
    fb = faces_b[start_b[pair] + local % count_b[pair]]
    # in chunks: objects overlapping far inside each other (a stability test's 100x sizes) put
    # every face of one near every face of the other, and all pairs at once ran out of memory
    plausible = _compiled(_plausible) if compiled else _plausible
    keep = torch.cat([plausible(tri, face_low, face_high, fa[k:k + CHUNK], fb[k:k + CHUNK], radius)
                      for k in range(0, len(fa), CHUNK)])
    fa, fb = fa[keep], fb[keep]
    if len(fa) == 0:
        return empty, idx, idx, idx
    measure = compiled_distance() if compiled else _distance
    dist = torch.cat([measure(tri[fa[k:k + CHUNK]], tri[fb[k:k + CHUNK]]) for k in range(0, len(fa), CHUNK)])
    close = dist < radius
    if not close.any():
        return empty, idx, idx, idx
    receiving, sending, corner = _closest_per_vertex(fa[close], fb[close], dist[close], graph)
    vectors, signed, p_s = _geometry(x, graph, receiving, sending, corner, compiled)
    tri_s = graph.faces[sending]
    nearest = (x[tri_s] - p_s[:, None]).norm(dim=-1).argmin(1)
    senders = tri_s.gather(1, nearest[:, None])[:, 0]
    return EdgeSet(senders, graph.faces[receiving, corner], vectors, signed), receiving, sending, corner


def face_edges(x: torch.Tensor, graph: GraphBatch, radius: float, compiled: bool = False) -> EdgeSet:
    """Face-face collision edges of positions x (N, 3) within `radius` (see the module's doc):
    `vectors` (E, 6) = [p_r - p_s, x_r - p_r], `signed` (E, 1). `compiled`: the plane test, the
    distances and the closest points of the triangle pairs through compiled code (a model rolled
    out with compile; a long training, gns.train.CONTACTS_COMPILE_STEPS)."""
    edges, receiving, sending, corner = _face_edges(x, graph, radius, compiled)
    if not (torch.is_grad_enabled() and x.requires_grad) or len(edges.senders) == 0:
        return edges
    vectors, signed, _ = _geometry(x, graph, receiving, sending, corner)
    return EdgeSet(edges.senders, edges.receivers, vectors, signed)
