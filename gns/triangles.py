"""Closest points between points, segments and triangles, computed on coordinate columns.

A vector here is a tuple of three (M,) tensors, its x, y and z columns, not an (M, 3) tensor of
rows: every operation is then elementwise on whole columns, with no reduction over a width-3
axis and no broadcasting of (M,) against (M, 3). On a CPU that runs the triangle-pair distance of
face edges ~2.5x faster than the same algebra on rows, eager and compiled (compiled, the columns
must be contiguous: `stacked` copies them so). The functions for rows (contacts.
closest_point_on_triangle, face_contacts.closest_points_on_triangles) convert at the edge.
"""
from __future__ import annotations

import torch

Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def columns(x: torch.Tensor) -> Vec:
    """Rows (M, 3) -> contiguous columns."""
    c = x.movedim(-1, 0).contiguous()
    return c[0], c[1], c[2]


def rows(v: Vec) -> torch.Tensor:
    """Columns -> rows (M, 3)."""
    return torch.stack(v, dim=-1)


def stacked(t: torch.Tensor) -> torch.Tensor:
    """Triangles (M, 3, 3) -> (3, 3, M), contiguous: vertex i's coordinate k is the column [i, k]
    (one copy of t; compiled code wants it made before it is entered)."""
    return t.permute(1, 2, 0).contiguous()


def vertices(s: torch.Tensor) -> list[Vec]:
    """The three vertices of stacked triangles (3, 3, M), as columns (views)."""
    return [(s[i, 0], s[i, 1], s[i, 2]) for i in range(3)]


def dot(u: Vec, v: Vec) -> torch.Tensor:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def sub(u: Vec, v: Vec) -> Vec:
    return u[0] - v[0], u[1] - v[1], u[2] - v[2]


def add(u: Vec, v: Vec) -> Vec:
    return u[0] + v[0], u[1] + v[1], u[2] + v[2]


def scale(u: Vec, s: torch.Tensor) -> Vec:
    return u[0] * s, u[1] * s, u[2] * s


def cross(u: Vec, v: Vec) -> Vec:
    return u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]


def norm(u: Vec) -> torch.Tensor:
    return torch.sqrt(dot(u, u))


def where(condition: torch.Tensor, u: Vec, v: Vec) -> Vec:
    return tuple(torch.where(condition, a, b) for a, b in zip(u, v))


def closest_point_on_triangle(p: Vec, a: Vec, b: Vec, c: Vec) -> Vec:
    """Closest points of triangles (a, b, c) to points p: the Voronoi-region test of Ericson,
    Real-Time Collision Detection, 5.1.5, vectorised with where."""
    tiny = torch.finfo(p[0].dtype).tiny
    ab, ac, ap = sub(b, a), sub(c, a), sub(p, a)
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = sub(p, b)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = sub(p, c)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    # inside the face, by barycentric coordinates
    denom = (va + vb + vc).clamp(min=tiny)
    out = add(a, add(scale(ab, vb / denom), scale(ac, vc / denom)))
    # edge regions (bc, ac, ab), then vertex regions (c, b, a): later assignments win
    w = (d4 - d3) / ((d4 - d3) + (d5 - d6)).clamp(min=tiny)
    out = where((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), add(b, scale(sub(c, b), w)), out)
    w = d2 / (d2 - d6).clamp(min=tiny)
    out = where((vb <= 0) & (d2 >= 0) & (d6 <= 0), add(a, scale(ac, w)), out)
    w = d1 / (d1 - d3).clamp(min=tiny)
    out = where((vc <= 0) & (d1 >= 0) & (d3 <= 0), add(a, scale(ab, w)), out)
    out = where((d6 >= 0) & (d5 <= d6), c, out)
    out = where((d3 >= 0) & (d4 <= d3), b, out)
    return where((d1 <= 0) & (d2 <= 0), a, out)


def closest_points_on_segments(p1: Vec, q1: Vec, p2: Vec, q2: Vec) -> tuple[Vec, Vec]:
    """Closest points of segments p1q1 and p2q2: Ericson 5.1.9, vectorised; parallel segments
    take s = 0 (any point of the overlap is as near)."""
    tiny = torch.finfo(p1[0].dtype).tiny
    d1, d2, r = sub(q1, p1), sub(q2, p2), sub(p1, p2)
    a, e = dot(d1, d1), dot(d2, d2)
    b, c, f = dot(d1, d2), dot(d1, r), dot(d2, r)
    denom = a * e - b * b
    s = torch.where(denom > 1e-12 * a * e, ((b * f - c * e) / denom.clamp(min=tiny)).clamp(0, 1), torch.zeros_like(a))
    t = (b * s + f) / e.clamp(min=tiny)
    # t outside [0, 1]: clamp it and recompute s for that end of the second segment
    s = torch.where(t < 0, (-c / a.clamp(min=tiny)).clamp(0, 1), torch.where(t > 1, ((b - c) / a.clamp(min=tiny)).clamp(0, 1), s))
    return add(p1, scale(d1, s)), add(p2, scale(d2, t.clamp(0, 1)))


def segment_through_triangle(p: Vec, q: Vec, a: Vec, b: Vec, c: Vec) -> tuple[Vec, torch.Tensor]:
    """Where segments pq pass through triangles (a, b, c): the points and whether they do (M,) bool."""
    n = cross(sub(b, a), sub(c, a))
    denom = dot(n, sub(q, p))
    s = dot(n, sub(a, p)) / torch.where(denom == 0, torch.ones_like(denom), denom)
    point = add(p, scale(sub(q, p), s))
    inside = (denom != 0) & (s >= 0) & (s <= 1)
    for u, v in ((a, b), (b, c), (c, a)):   # on the inner side of every edge
        inside = inside & (dot(cross(sub(v, u), sub(point, u)), n) >= 0)
    return point, inside


def _cat(vs: list[Vec]) -> Vec:
    return tuple(torch.cat([v[k] for v in vs]) for k in range(3))


def _candidates(t1: list[Vec], t2: list[Vec]) -> tuple[Vec, Vec, torch.Tensor]:
    """The 21 candidate closest-point pairs of triangles t1 and t2 (three vertices each, M
    triangles), in order: each vertex against the other triangle (6), each edge against each edge
    (9), and where an edge of one passes through the other (6, at distance 0; infinity where it
    does not). Each kind is one call on all its candidates at once (21 calls of M cost ~3x as much
    eager). Returns the points on t1 and on t2 (columns of 21 M) and the distances (21, M)."""
    m = len(t1[0][0])
    # each vertex of t1, then of t2, against the other triangle
    points = _cat(t1 + t2)
    near = closest_point_on_triangle(points, *(_cat([t2[i]] * 3 + [t1[i]] * 3) for i in range(3)))
    vertex_1 = tuple(torch.cat([p[:3 * m], q[3 * m:]]) for p, q in zip(points, near))
    vertex_2 = tuple(torch.cat([q[:3 * m], p[3 * m:]]) for p, q in zip(points, near))
    pairs = [(i, j) for i in range(3) for j in range(3)]
    edge_1, edge_2 = closest_points_on_segments(_cat([t1[i] for i, _ in pairs]), _cat([t1[(i + 1) % 3] for i, _ in pairs]),
                                                _cat([t2[j] for _, j in pairs]), _cat([t2[(j + 1) % 3] for _, j in pairs]))
    crossing, through = segment_through_triangle(
        _cat([t1[k] for k in range(3)] + [t2[k] for k in range(3)]),
        _cat([t1[(k + 1) % 3] for k in range(3)] + [t2[(k + 1) % 3] for k in range(3)]),
        *(_cat([t2[i]] * 3 + [t1[i]] * 3) for i in range(3)))
    dist = torch.cat([norm(sub(vertex_1, vertex_2)), norm(sub(edge_1, edge_2)),
                      torch.where(through, 0.0, torch.inf).to(crossing[0].dtype)]).view(21, m)
    return _cat([vertex_1, edge_1, crossing]), _cat([vertex_2, edge_2, crossing]), dist


def _each_candidate(t1: list[Vec], t2: list[Vec]):
    """The same 21 candidates as _candidates, in the same order, one at a time: (point on t1,
    point on t2, distance (M,)). Compiled code fuses them into one loop over M (1.5x faster
    than the calls by kind compiled); eager, the calls by kind are faster."""
    for own, other, first in ((t1, t2, True), (t2, t1, False)):
        for v in own:
            near = closest_point_on_triangle(v, *other)
            yield (v, near, norm(sub(v, near))) if first else (near, v, norm(sub(v, near)))
    for i in range(3):
        for j in range(3):
            p, q = closest_points_on_segments(t1[i], t1[(i + 1) % 3], t2[j], t2[(j + 1) % 3])
            yield p, q, norm(sub(p, q))
    for own, other in ((t1, t2), (t2, t1)):
        for k in range(3):
            point, through = segment_through_triangle(own[k], own[(k + 1) % 3], *other)
            yield point, point, torch.where(through, 0.0, torch.inf).to(point[0].dtype)


def triangle_distance(t1: list[Vec], t2: list[Vec], compiled: bool = False) -> torch.Tensor:
    """The distance (M,) between triangles t1 and t2 (three vertices each). `compiled`: written
    for compiled code (the candidates one at a time)."""
    if not compiled:
        return _candidates(t1, t2)[2].amin(dim=0)
    best = None
    for _, _, d in _each_candidate(t1, t2):
        best = d if best is None else torch.minimum(best, d)
    return best


def closest_points_on_triangles(t1: list[Vec], t2: list[Vec], compiled: bool = False) -> tuple[Vec, Vec]:
    """Closest points on triangles t1 and t2 (three vertices each): the nearest candidate, the
    first of equal ones; triangles that cross meet where an edge of one passes through the other.
    `compiled`: written for compiled code (the candidates one at a time)."""
    if not compiled:
        on_1, on_2, dist = _candidates(t1, t2)
        m = dist.shape[1]
        pick = dist.argmin(dim=0) * m + torch.arange(m, device=dist.device)
        return tuple(c[pick] for c in on_1), tuple(c[pick] for c in on_2)
    best = None
    for p, q, d in _each_candidate(t1, t2):
        if best is None:
            best, on_1, on_2 = d, p, q
            continue
        nearer = d < best
        best, on_1, on_2 = torch.where(nearer, d, best), where(nearer, p, on_1), where(nearer, q, on_2)
    return on_1, on_2
