"""Graphs: mesh edges from triangles, and packing many object graphs into one batch.

Convention used everywhere in gns: an edge k goes from `senders[k]` to `receivers[k]`; its
message is summed at the receiver. Mesh edges come in both directions, so every undirected
mesh edge is two graph edges. A batch is one big graph whose nodes are the vertices of all its
objects, numbered graph after graph (node offset per graph); `node_graph[i]` names the graph of
node i. Further edge sets are extra `EdgeSet` fields: `collision_edges` join vertices of
different objects of the same scene (`graph_scene[g]` names the scene of graph g within the
batch) that are closer than a radius; see gns.contacts.collision_edges.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, fields, replace

import numpy as np
import torch


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Directed edges of a triangle mesh, both directions, without duplicates.

    faces: (F, 3) vertex indices. Returns (E, 2) int64 [sender, receiver], sorted.
    """
    faces = np.asarray(faces, np.int64)
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    pairs = np.concatenate([pairs, pairs[:, ::-1]])
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    # one int64 key a pair, ordered as the pairs are: np.unique on rows (axis=0) is ~20x slower,
    # and ensembles rebuild a whole batch's edges every step (gns.ensemble.with_surface_edges)
    base = int(pairs.max(initial=-1)) + 1
    keys = np.unique(pairs[:, 0] * base + pairs[:, 1])
    return np.stack([keys // base, keys % base], axis=1)


def centre_spokes(num_vertices: int) -> np.ndarray:
    """Edges both ways between vertices 0 .. n-1 and a centre node n: (2n, 2) int64.

    On a mesh graph a contact reaches a vertex only after as many message-passing steps as
    there are edges between them; the MOVi-A sphere and beveled cube are 6 edges across, more
    than the `gns_cpu` preset's 5 steps, so the far side of an object never heard of a
    contact, and shape matching averaged its silence into too little spin. Through a centre
    node every vertex is 2 steps from every other. The centre is an ordinary node (rest
    position 0, the centre of mass) and the spokes ordinary mesh edges, so the network keeps
    its parameters: a model without it can be fine-tuned with it.
    """
    ring = np.arange(num_vertices, dtype=np.int64)
    centre = np.full(num_vertices, num_vertices, np.int64)
    return np.concatenate([np.stack([ring, centre], 1), np.stack([centre, ring], 1)])


@dataclass
class EdgeSet:
    senders: torch.Tensor    # (E,) int64 node index
    receivers: torch.Tensor  # (E,) int64 node index
    vectors: torch.Tensor | None = None  # (E, 3) edge geometry when it is not x_r - x_s (gns.contacts)
    signed: torch.Tensor | None = None   # (E, 1) signed distance, with `vectors`

    def to(self, device) -> "EdgeSet":
        return EdgeSet(*(None if t is None else t.to(device)
                         for t in (self.senders, self.receivers, self.vectors, self.signed)))


@dataclass
class GraphBatch:
    """A packed batch of object graphs (one graph = one object in one window)."""

    mesh_edges: EdgeSet
    rest: torch.Tensor        # (N, 3) float64 scaled rest vertex, body frame (centre of mass at 0)
    material: torch.Tensor    # (N, 2) float32 friction, restitution of the node's object
    node_graph: torch.Tensor  # (N,) int64 graph index of each node
    num_graphs: int
    graph_scene: torch.Tensor | None = None       # (G,) int64 scene (within the batch) of each graph
    collision_edges: EdgeSet | None = None        # between objects of a scene; see `collision_edges`
    faces: torch.Tensor | None = None             # (F, 3) int64 node indices of each object's triangles
    # body-frame symmetries of each graph's rest shape (G, K, 3, 3), padded; with their counts (G,)
    symmetries: torch.Tensor | None = None
    num_symmetries: torch.Tensor | None = None

    @property
    def num_nodes(self) -> int:
        return self.rest.shape[0]

    @property
    def node_scene(self) -> torch.Tensor:
        """(N,) scene of each node's object; every graph its own scene when no grouping is set."""
        if self.graph_scene is None:
            return self.node_graph
        return self.graph_scene[self.node_graph]

    def to(self, device) -> "GraphBatch":
        moved = {f.name: getattr(self, f.name) for f in fields(self)}
        for name, value in moved.items():
            if isinstance(value, (torch.Tensor, EdgeSet)):
                moved[name] = value.to(device)
        return GraphBatch(**moved)


def _signed_permutations() -> np.ndarray:
    """The 24 proper rotations that permute the coordinate axes (with signs): (24, 3, 3)."""
    import itertools
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return np.stack(out)


def mesh_symmetries(vertices: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Proper rotations S among the axis permutations that map the vertex set onto itself (K, 3, 3),
    identity first.

    A vertex at rest position r may then be described as at S r (with the pose R S^T): the same
    object, relabelled. Cubes have all 24; a cylinder about z those that keep its axis and its
    segments; a mesh without such symmetry only the identity.
    """
    v = np.ascontiguousarray(vertices, np.float64)
    # remembered by the vertices' bytes: every rollout of a dataset's scenes packs its meshes again
    # (MeshLibrary), and finding these was ~2% of rolling out 400 MOVi-A scenes
    return _symmetries_of(v.tobytes(), v.shape, tol).copy()


@functools.lru_cache(maxsize=256)
def _symmetries_of(data: bytes, shape: tuple, tol: float) -> np.ndarray:
    v = np.frombuffer(data, np.float64).reshape(shape)
    scale = max(float(np.abs(v).max()), 1e-12)
    keep = []
    for s in _signed_permutations():
        moved = v @ s.T
        d = np.sqrt(((moved[:, None, :] - v[None, :, :]) ** 2).sum(-1)).min(axis=1)
        if d.max() <= tol * scale:
            keep.append(s)
    keep.sort(key=lambda s: not np.allclose(s, np.eye(3)))
    return np.stack(keep)


def padded_groups(groups: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetry groups of different sizes (K_i, 3, 3) -> padded (len, max K, 3, 3) float64 (identity
    beyond each group) and their sizes (len,)."""
    counts = [len(g) for g in groups]
    padded = np.tile(np.eye(3), (len(groups), max(counts), 1, 1))
    for i, g in enumerate(groups):
        padded[i, :len(g)] = g
    return torch.from_numpy(padded), torch.tensor(counts)


def ragged_arange(counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For counts (B,): the owner (sum counts,) of each element and its index within its owner."""
    owner = torch.repeat_interleave(torch.arange(len(counts), device=counts.device), counts)
    starts = torch.cumsum(counts, 0) - counts
    return owner, torch.arange(int(counts.sum()), device=counts.device) - starts[owner]


def graph_settings(features_cfg) -> dict:
    """MeshLibrary's keyword arguments for the graphs a network trained with `features_cfg` reads:
    centre nodes and spokes (features.centre_node, surface_edges)."""
    return dict(centre_node=bool(getattr(features_cfg, "centre_node", False)),
                surface_edges=bool(getattr(features_cfg, "surface_edges", True)))


class MeshLibrary:
    """The dataset's rest meshes, stored once, from which batches of graphs are packed."""

    def __init__(self, meshes: dict[str, tuple[np.ndarray, np.ndarray]], centre_node: bool = False,
                 surface_edges: bool = True):
        """centre_node: each graph also has a node at its centre of mass joined to every vertex
        (centre_spokes); surface_edges=False (with centre_node) keeps only those spokes."""
        self.names = sorted(meshes)
        self.index = {name: i for i, name in enumerate(self.names)}
        verts = [np.asarray(meshes[n][0], np.float64) for n in self.names]
        edges = [mesh_edges(meshes[n][1]) for n in self.names]
        if not (centre_node or surface_edges):
            raise ValueError("a graph without surface edges needs a centre node (features.centre_node)")
        if centre_node:
            edges = [np.concatenate([e if surface_edges else e[:0], centre_spokes(len(v))])
                     for v, e in zip(verts, edges)]
            verts = [np.concatenate([v, np.zeros((1, 3))]) for v in verts]
        for name, v, e in zip(self.names, verts, edges):
            if len(e) and e.max() >= len(v):
                raise ValueError(f"mesh {name!r}: a face names vertex {e.max()}, it has {len(v)}")
        self.num_vertices = torch.tensor([len(v) for v in verts])
        self.num_edges = torch.tensor([len(e) for e in edges])
        self._vertex_start = torch.cumsum(self.num_vertices, 0) - self.num_vertices
        self._edge_start = torch.cumsum(self.num_edges, 0) - self.num_edges
        self._vertices = torch.from_numpy(np.concatenate(verts))
        self.radius = torch.tensor([np.linalg.norm(v, axis=1).max() for v in verts])  # bounding sphere of the unit mesh
        self._edges = torch.from_numpy(np.concatenate(edges))
        faces = [np.asarray(meshes[n][1], np.int64).reshape(-1, 3) for n in self.names]
        self.num_faces = torch.tensor([len(f) for f in faces])
        self._face_start = torch.cumsum(self.num_faces, 0) - self.num_faces
        self._faces = torch.from_numpy(np.concatenate(faces))
        # body-frame symmetries of each mesh (augment.body_symmetry), padded to the largest group
        self._symmetries, self.num_symmetries = padded_groups([mesh_symmetries(v) for v in verts])

    def random_symmetries(self, shape_ids: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        """One random body-frame symmetry of each graph's mesh (B, 3, 3) float64 (see mesh_symmetries)."""
        count = self.num_symmetries[shape_ids]
        pick = torch.from_numpy(np.floor(rng.random(len(shape_ids)) * count.numpy()).astype(np.int64))
        return self._symmetries[shape_ids, pick]

    def shape_ids(self, names: list[str]) -> torch.Tensor:
        missing = [n for n in names if n not in self.index]
        if missing:
            raise ValueError(f"shape {missing[0]!r} has no mesh; meshes: {', '.join(self.names)}")
        return torch.tensor([self.index[n] for n in names], dtype=torch.int64, device=self._vertices.device)

    def pack(self, shape_ids: torch.Tensor, scale: torch.Tensor, friction: torch.Tensor,
             restitution: torch.Tensor, graph_scene: torch.Tensor | None = None) -> GraphBatch:
        """One graph per entry of shape_ids (B,), with per-graph scale, friction, restitution (B,).

        graph_scene (B,): the scene of each graph within the batch (graphs of one scene interact
        through collision edges); None = every graph alone.
        """
        n_vert = self.num_vertices[shape_ids]
        node_graph, local = ragged_arange(n_vert)
        library_node = self._vertex_start[shape_ids][node_graph] + local
        rest = self._vertices[library_node] * scale.to(torch.float64)[node_graph, None]

        n_edge = self.num_edges[shape_ids]
        edge_graph, local_edge = ragged_arange(n_edge)
        library_edge = self._edge_start[shape_ids][edge_graph] + local_edge
        node_offset = torch.cumsum(n_vert, 0) - n_vert
        edges = self._edges[library_edge] + node_offset[edge_graph, None]

        face_graph, local_face = ragged_arange(self.num_faces[shape_ids])
        faces = self._faces[self._face_start[shape_ids][face_graph] + local_face] + node_offset[face_graph, None]

        material = torch.stack([friction, restitution], dim=1).to(torch.float32)[node_graph]
        ids = shape_ids.cpu()
        return GraphBatch(EdgeSet(edges[:, 0].contiguous(), edges[:, 1].contiguous()), rest, material,
                          node_graph, len(shape_ids), graph_scene, faces=faces,
                          symmetries=self._symmetries[ids].to(rest), num_symmetries=self.num_symmetries[ids].to(rest.device))


def alone_in_scenes(graph: GraphBatch) -> bool:
    """Whether no scene of the batch holds two of its graphs (always, without `graph_scene`)."""
    return graph.graph_scene is None or len(torch.unique(graph.graph_scene)) == graph.num_graphs


def per_graph(values: torch.Tensor, graph: GraphBatch, reduce: str, owner: torch.Tensor | None = None) -> torch.Tensor:
    """Node values (N, ...) reduced over each graph's nodes -> (G, ...); reduce is "amax",
    "amin" or "sum". Values of other items (edges) need their `owner` graph (len(values),)."""
    fill = {"amax": -torch.inf, "amin": torch.inf, "sum": 0.0}[reduce]
    owner = graph.node_graph if owner is None else owner
    index = owner.view(-1, *[1] * (values.dim() - 1)).expand_as(values)
    out = torch.full((graph.num_graphs, *values.shape[1:]), fill, dtype=values.dtype, device=values.device)
    return out.scatter_reduce(0, index, values, reduce)


def graph_centres(x: torch.Tensor, graph: GraphBatch) -> torch.Tensor:
    """Mean vertex position of each graph (G, 3) from positions x (N, 3)."""
    count = torch.bincount(graph.node_graph, minlength=graph.num_graphs).to(x.dtype)
    return per_graph(x, graph, "sum") / count[:, None]


def graph_sizes(graph: GraphBatch) -> torch.Tensor:
    """Largest axis extent of each graph's scaled rest mesh (G,): the object's size."""
    return (per_graph(graph.rest, graph, "amax") - per_graph(graph.rest, graph, "amin")).max(dim=1).values


def select_graphs(graph: GraphBatch, keep: torch.Tensor) -> tuple[GraphBatch, torch.Tensor]:
    """The batch of the graphs with keep (G,) True, renumbered, and the (n,) indices of its nodes
    in `graph`. Edges (mesh, collision) and faces are kept where both ends are kept: a graph left
    out must share no collision edge with one kept (the caller's rule), else the kept one would
    lose its contact."""
    return _subgraph(graph, keep[graph.node_graph], keep)


def select_nodes(graph: GraphBatch, node_keep: torch.Tensor) -> tuple[GraphBatch, torch.Tensor]:
    """The batch with only the nodes where node_keep (N,) is True, every graph kept (each must keep
    a node), and the (n,) indices of those nodes in `graph`. Edges and faces are kept where all
    their nodes are."""
    return _subgraph(graph, node_keep, None)


def select_graph_nodes(graph: GraphBatch, node_keep: torch.Tensor, keep: torch.Tensor) -> tuple[GraphBatch, torch.Tensor]:
    """select_graphs(graph, keep) and then select_nodes of it, in one cut: the graphs with keep (G,)
    True and of their nodes those with node_keep (N,) (False outside them; each kept graph must
    keep a node), and those nodes' indices in `graph`."""
    return _subgraph(graph, node_keep, keep)


def _subgraph(graph: GraphBatch, node_keep: torch.Tensor, keep: torch.Tensor | None) -> tuple[GraphBatch, torch.Tensor]:
    """`keep` (G,) the graphs kept, None for all (their per-graph fields are then not copied)."""
    nodes = node_keep.nonzero()[:, 0]
    new_node = torch.cumsum(node_keep, 0) - 1       # index of a kept node in the selection
    if keep is None:   # select_nodes, every rollout step of a features.lowest_vertices model
        per = lambda t: t  # noqa: E731
        node_graph = graph.node_graph.index_select(0, nodes)
        num_graphs = graph.num_graphs
    else:
        per = lambda t: t[keep]  # noqa: E731
        node_graph = (torch.cumsum(keep, 0) - 1)[graph.node_graph[nodes]]
        num_graphs = int(keep.sum())

    def edges(e: EdgeSet | None) -> EdgeSet | None:
        if e is None:
            return None
        # index_select at the kept positions: indexing with the boolean mask costs ~3x as much
        ok = (node_keep.index_select(0, e.senders) & node_keep.index_select(0, e.receivers)).nonzero()[:, 0]
        pick = lambda t: None if t is None else t.index_select(0, ok)  # noqa: E731
        return EdgeSet(new_node.index_select(0, pick(e.senders)), new_node.index_select(0, pick(e.receivers)),
                       pick(e.vectors), pick(e.signed))

    faces = None
    if graph.faces is not None:
        whole = node_keep.index_select(0, graph.faces.reshape(-1)).view(-1, 3).all(dim=1).nonzero()[:, 0]
        faces = new_node.index_select(0, graph.faces.index_select(0, whole).view(-1)).view(-1, 3)
    return replace(graph, mesh_edges=edges(graph.mesh_edges), rest=graph.rest.index_select(0, nodes),
                   material=graph.material.index_select(0, nodes), node_graph=node_graph, num_graphs=num_graphs,
                   graph_scene=None if graph.graph_scene is None else per(graph.graph_scene),
                   collision_edges=edges(graph.collision_edges), faces=faces,
                   symmetries=None if graph.symmetries is None else per(graph.symmetries),
                   num_symmetries=None if graph.num_symmetries is None else per(graph.num_symmetries)), nodes


def lowest_nodes(z: torch.Tensor, graph: GraphBatch, k: int, top: int = 0) -> torch.Tensor:
    """(N,) bool: the k nodes of each graph lowest in z (N,) (ties: the lower index), its `top`
    highest and its last node, the centre node of a graph that has one (MeshLibrary puts it last)."""
    node_graph = graph.node_graph
    count = torch.bincount(node_graph, minlength=graph.num_graphs)
    start = torch.cumsum(count, 0) - count
    key = z.clone()
    key[start + count - 1] = -torch.inf
    # each graph's heights in a row of a (G, most nodes) table padded with +inf, sorted row by row:
    # ~3x faster than sorting all nodes and then by graph (a rollout does this every step)
    width = int(count.max()) if len(count) else 0
    slot = node_graph * width + (torch.arange(len(z), device=z.device) - start.index_select(0, node_graph))
    table = z.new_full((graph.num_graphs * width,), torch.inf).index_copy(0, slot, key).view(graph.num_graphs, width)
    order = torch.sort(table, dim=1, stable=True).indices
    rank = torch.empty_like(order).scatter_(1, order, torch.arange(width, device=z.device).expand_as(order))
    rank = rank.view(-1).index_select(0, slot)
    return (rank <= k) | (rank >= (count - top).index_select(0, node_graph))
