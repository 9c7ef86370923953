"""The branch graph of a voxel skeleton: nodes (open ends, junctions) joined by axis polylines.

The skeleton's voxels are linked to their 26 neighbours in one sparse matrix
(``scipy.sparse``); its connected components (``scipy.sparse.csgraph``) give
the junction clusters (voxels with three or more neighbours, which thinning
leaves in small clumps) and the simple paths between them.  Each path is
ordered by a depth-first walk from one of its ends.  Then, on the small graph:

* spur pruning: a terminal edge shorter than ``k`` radii of the vessel it
  leaves, or thinner than a quarter of that radius, is a thinning artefact
  (a bump or fin of the wall), not a branch; the most spur-like one is removed
  and the graph simplified, until none is left.  The vessel's radius is the
  larger of the inscribed radius at the junction and the median radius of the
  thickest other edge there, so that the spur trees of a rough wall, whose
  junctions lie near the wall, go as well;
* junction clusters closer than a fraction of the local radius are merged
  into one node (a trifurcation seen by thinning as two close forks);
* nodes left with two edges are dissolved (their edges joined);
* loops (handles of a rough lumen) are cut, keeping the spanning tree of
  least length-over-radius, and the above is repeated.

No library offers this with radius-relative pruning (skan, the maintained
skeleton-graph package, is not a dependency and prunes by length only).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

#: Half of the 26-neighbourhood (the other half is the same pairs seen from the other side).
#: Terminal edges thinner than this fraction of the radius at their junction are pruned whatever their length.
THIN = 0.25
_OFFSETS = np.array([o for o in itertools.product((-1, 0, 1), repeat=3) if o > (0, 0, 0)])


@dataclass
class Edge:
    """An axis polyline between nodes ``a`` and ``b``; ``points`` (n, 3) in mm, from a to b, ends included."""

    a: int
    b: int
    points: np.ndarray
    median_radius: float = float("nan")  # cached by ``_edge_radius``

    @property
    def length(self) -> float:
        """Arc length, mm."""
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    def other(self, node: int) -> int:
        """The node at the other end from ``node``."""
        return self.b if node == self.a else self.a

    def from_node(self, node: int) -> np.ndarray:
        """The points ordered from ``node`` to the other end, shape (n, 3)."""
        return self.points if node == self.a else self.points[::-1]


@dataclass
class Graph:
    """Nodes (m, 3) in mm and the edges between them."""

    nodes: np.ndarray
    edges: list[Edge] = field(default_factory=list)

    def degree(self) -> np.ndarray:
        """Number of edge ends at each node, shape (m,)."""
        deg = np.zeros(len(self.nodes), int)
        for e in self.edges:
            deg[e.a] += 1
            deg[e.b] += 1
        return deg

    def incident(self, node: int) -> list[int]:
        """Indices of the edges touching ``node``."""
        return [i for i, e in enumerate(self.edges) if node in (e.a, e.b)]


def voxel_adjacency(skel: np.ndarray) -> tuple[np.ndarray, sparse.csr_matrix]:
    """Skeleton voxels and their 26-neighbour adjacency.

    Returns
    -------
    kji : ndarray of int, shape (n, 3)
        Voxel indices, in C order.
    adjacency : csr_matrix of bool, shape (n, n)
        Symmetric.
    """
    kji = np.argwhere(skel)
    flat = np.ravel_multi_index(kji.T, skel.shape)
    rows, cols = [], []
    for off in _OFFSETS:
        nb = kji + off
        ok = np.flatnonzero(np.all((nb >= 0) & (nb < skel.shape), axis=1))
        target = np.ravel_multi_index(nb[ok].T, skel.shape)
        pos = np.minimum(np.searchsorted(flat, target), len(flat) - 1)
        hit = flat[pos] == target
        rows.append(ok[hit])
        cols.append(pos[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    n = len(kji)
    adjacency = sparse.coo_matrix((np.ones(2 * len(r), bool), (np.r_[r, c], np.r_[c, r])), shape=(n, n)).tocsr()
    return kji, adjacency


def skeleton_graph(skel: np.ndarray, to_world) -> Graph:
    """The branch graph of a voxel skeleton.

    Parameters
    ----------
    skel : ndarray of bool, shape (nk, nj, ni)
    to_world : callable
        Maps voxel indices (n, 3) (k, j, i) to points (n, 3) in mm, e.g. ``Volume.index_to_world``.

    Returns
    -------
    Graph
        Nodes are junction clusters (at their centroid) and end voxels; self-loops are dropped, and so
        is every skeleton piece but the largest.
    """
    kji, adj = voxel_adjacency(skel)
    _, piece = csgraph.connected_components(adj, directed=False)
    keep = np.flatnonzero(piece == np.argmax(np.bincount(piece)))  # specks of skeleton in cavities go
    kji, adj = kji[keep], adj[keep][:, keep]
    xyz = to_world(kji.astype(float))
    degree = np.asarray(adj.sum(axis=1)).ravel()
    junction = degree >= 3
    j_idx = np.flatnonzero(junction)
    # Junction voxels are clustered when adjacent, or when one path voxel touches both (else that voxel
    # could attach its path to only one of them and the graph would fall apart).
    touch = adj[np.flatnonzero(~junction)][:, j_idx].astype(np.int32)
    linked = (adj[j_idx][:, j_idx].astype(np.int32) + touch.T @ touch) > 0
    n_clusters, cluster = csgraph.connected_components(linked, directed=False)
    node_of = np.full(len(kji), -1)
    node_of[j_idx] = cluster
    nodes = [np.array([xyz[j_idx[cluster == c]].mean(axis=0) for c in range(n_clusters)]).reshape(-1, 3)]
    ends = np.flatnonzero(degree <= 1)
    node_of[ends] = n_clusters + np.arange(len(ends))
    nodes.append(xyz[ends])
    all_nodes = np.concatenate(nodes)

    p_idx = np.flatnonzero(~junction)
    sub = adj[p_idx][:, p_idx]
    n_paths, path = csgraph.connected_components(sub, directed=False)
    sub_degree = np.asarray(sub.sum(axis=1)).ravel()
    members_of = np.split(np.argsort(path, kind="stable"), np.cumsum(np.bincount(path, minlength=n_paths))[:-1])
    edges = []
    for members in members_of:
        start = members[np.argmin(sub_degree[members])]
        order = p_idx[csgraph.depth_first_order(sub, start, directed=False, return_predecessors=False)]
        ends_at = [_attach(order[0], node_of, adj, junction, exclude=-1)]
        ends_at.append(_attach(order[-1], node_of, adj, junction, exclude=ends_at[0] if len(order) == 1 else -1))
        if min(ends_at) < 0 or ends_at[0] == ends_at[1]:
            continue  # an isolated ring or voxel, or a loop on one junction cluster
        pts = xyz[order]
        pts = np.concatenate([all_nodes[[ends_at[0]]], pts, all_nodes[[ends_at[1]]]])
        keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9]
        edges.append(Edge(ends_at[0], ends_at[1], pts[keep]))
    return Graph(all_nodes, edges)


def _attach(voxel: int, node_of: np.ndarray, adj: sparse.csr_matrix, junction: np.ndarray, exclude: int) -> int:
    """The node at which a path ending in ``voxel`` ends: its own end node, or a neighbouring junction
    cluster (other than ``exclude`` when there is a choice); -1 if none."""
    if node_of[voxel] >= 0:
        return int(node_of[voxel])
    nbrs = adj.indices[adj.indptr[voxel]:adj.indptr[voxel + 1]]
    clusters = [int(c) for c in np.unique(node_of[nbrs[junction[nbrs]]])]
    if not clusters:
        return -1
    others = [c for c in clusters if c != exclude]
    return others[0] if others else clusters[0]


def _dissolve_degree_two(graph: Graph) -> None:
    """Join the two edges of every node that has exactly two (in place)."""
    while True:
        deg = graph.degree()
        twos = [n for n in np.flatnonzero(deg == 2) if len(graph.incident(n)) == 2]
        if not twos:
            return
        node = twos[0]
        i, j = graph.incident(node)
        e, f = graph.edges[i], graph.edges[j]
        a, b = e.other(node), f.other(node)
        points = np.concatenate([e.from_node(a), f.from_node(node)[1:]])
        graph.edges = [g for k, g in enumerate(graph.edges) if k not in (i, j)]
        if a != b:  # a ring closing on itself is dropped
            graph.edges.append(Edge(a, b, points))


def _drop_parallel(graph: Graph) -> None:
    """Of several edges joining the same two nodes (a loop of the skeleton), keep the shortest (in place)."""
    best: dict[tuple[int, int], Edge] = {}
    for e in graph.edges:
        key = (min(e.a, e.b), max(e.a, e.b))
        if key not in best or e.length < best[key].length:
            best[key] = e
    graph.edges = list(best.values())


def simplify(graph: Graph, radius_at, prune: float, merge: float) -> Graph:
    """Prune spurs, merge close junctions, dissolve degree-2 nodes; returns a compacted graph.

    Parameters
    ----------
    graph : Graph
    radius_at : callable
        Vessel radius (mm) at points (n, 3) mm: the depth ``-phi`` of the level set.
    prune : float
        A terminal edge shorter than ``prune`` times the radius of the vessel it leaves is removed, and so
        is one whose median radius is below ``THIN`` times that radius (a fin of the wall, not a vessel).
    merge : float
        Two junctions joined by an edge shorter than ``merge`` times their larger radius become one node.

    Returns
    -------
    Graph
    """
    graph = Graph(graph.nodes.copy(), list(graph.edges))
    _dissolve_degree_two(graph)
    _drop_parallel(graph)
    while True:
        _prune_and_merge(graph, radius_at, prune, merge)
        if not _break_cycles(graph, radius_at):
            return _compact(graph)


def _edge_radius(edge: Edge, radius_at) -> float:
    """Median radius along an edge, mm (cached on the edge)."""
    if not np.isfinite(edge.median_radius):
        edge.median_radius = float(np.median(radius_at(edge.points)))
    return edge.median_radius


def _break_cycles(graph: Graph, radius_at) -> bool:
    """Cut the loops of the graph (handles of a rough lumen), keeping its cheapest spanning tree where an edge
    costs its length over its radius (thick, short connections are kept).  Returns whether any edge was cut."""
    n_nodes = len(graph.nodes)
    n_comp, _ = csgraph.connected_components(_node_matrix(graph, np.ones(len(graph.edges))), directed=False)
    used = len({n for e in graph.edges for n in (e.a, e.b)})
    if len(graph.edges) <= used - (n_comp - (n_nodes - used)):
        return False
    cost = np.array([e.length / max(_edge_radius(e, radius_at), 1e-3) + 1e-9 for e in graph.edges])
    tree = csgraph.minimum_spanning_tree(_node_matrix(graph, cost)).tocoo()
    keep = {(min(i, j), max(i, j)) for i, j in zip(tree.row, tree.col)}
    graph.edges = [e for e in graph.edges if (min(e.a, e.b), max(e.a, e.b)) in keep]
    _dissolve_degree_two(graph)
    return True


def _node_matrix(graph: Graph, weight: np.ndarray) -> sparse.csr_matrix:
    """Sparse node-by-node matrix with ``weight[k]`` at the entry of edge k (one entry per node pair)."""
    n = len(graph.nodes)
    a = np.array([e.a for e in graph.edges], int)
    b = np.array([e.b for e in graph.edges], int)
    return sparse.coo_matrix((weight, (np.minimum(a, b), np.maximum(a, b))), shape=(n, n)).tocsr()


def _prune_and_merge(graph: Graph, radius_at, prune: float, merge: float) -> None:
    """Remove spurs one at a time and merge close junctions until neither is left (in place)."""
    while True:
        deg = graph.degree()
        radius = radius_at(graph.nodes)
        spurs = []
        for k, e in enumerate(graph.edges):
            if min(deg[e.a], deg[e.b]) == 1 and max(deg[e.a], deg[e.b]) >= 3:
                junction = e.a if deg[e.b] == 1 else e.b
                parent = max(_edge_radius(graph.edges[i], radius_at) for i in graph.incident(junction) if i != k)
                r_ref = max(radius[junction], parent, 1e-6)
                thin = _edge_radius(e, radius_at) < THIN * r_ref
                spurs.append((0.0 if thin else e.length / r_ref, k))
        spurs = [s for s in spurs if s[0] < prune]
        if spurs:
            del graph.edges[min(spurs)[1]]
        else:
            short = [(e.length, k) for k, e in enumerate(graph.edges)
                     if deg[e.a] >= 3 and deg[e.b] >= 3 and e.length < merge * max(radius[e.a], radius[e.b])]
            if not short:
                return
            e = graph.edges.pop(min(short)[1])
            graph.nodes[e.a] = 0.5 * (graph.nodes[e.a] + graph.nodes[e.b])
            for f in graph.edges:  # re-attach the other edges of b to a, moving their end point
                for end, attr in ((0, "a"), (-1, "b")):
                    if getattr(f, attr) == e.b:
                        setattr(f, attr, e.a)
                        f.points = f.points.copy()
                        f.points[end] = graph.nodes[e.a]
                    elif getattr(f, attr) == e.a:
                        f.points = f.points.copy()
                        f.points[end] = graph.nodes[e.a]
        _dissolve_degree_two(graph)
        _drop_parallel(graph)


def _compact(graph: Graph) -> Graph:
    """Drop nodes that no edge uses and renumber."""
    used = sorted({n for e in graph.edges for n in (e.a, e.b)})
    new = {old: k for k, old in enumerate(used)}
    return Graph(graph.nodes[used].reshape(-1, 3), [Edge(new[e.a], new[e.b], e.points) for e in graph.edges])
