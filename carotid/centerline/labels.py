"""Naming the branches of the pruned graph: CCA, ICA, ECA and side branches.

The rules (each cue is recorded in ``Centerlines.info["labelling"]``):

**CCA, the inflow trunk.**  Every open end (graph node of degree 1) is scored
by three cues and the best is the CCA inlet:

* thickness at the end: the median radius over the last four radii of axis
  before the open end, divided by the largest such radius (weight 1).  Vessels
  taper downstream, so the inlet is the thickest end even where a daughter
  (an ICA with its bulb) is thicker on average;
* topology: at its junction the trunk points away from the daughters, so the
  mean cosine between its direction and those of the other edges there is
  strongly negative; the score adds half of minus that mean (weight 0.5);
* orientation, for a neck CTA in the LPS frame: the lowest open end (least z)
  gets 0.25.  It only breaks near-ties, so a surface not stored z-up is still
  labelled by thickness and topology.

**Bifurcation.**  From the inlet the CCA is followed downstream; the first
junction where the second-largest child edge has at least 0.4 times the median
radius of the largest is the carotid bifurcation.  Smaller children on the way
are CCA side branches (``branch<k>``).  Each daughter is then followed to an
open end, continuing at each further junction into the child that is thickest
and best aligned with the incoming direction.

**ICA or ECA.**  Votes for one daughter being the ICA, each +1 or -1:

* sinus bulb: the larger mean radius just beyond the bifurcation (from one to
  three junction radii of arc);
* the ICA gives no branches in the neck: fewer side branches along it;
* the ICA is the larger vessel: larger median radius over its whole length;
* posterior course, only when the CCA runs up the z axis (a neck CTA in LPS):
  the ICA heads more posteriorly (+y) than the ECA.

The sum decides; the bulb breaks ties.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from carotid.centerline.axes import arclength
from carotid.centerline.graph import Edge, Graph

#: A child edge at least this fraction of the thickest child's radius makes the junction a bifurcation.
DAUGHTER_FRACTION = 0.4


@dataclass
class Labelled:
    """Named raw axis paths (before smoothing), oriented as in ``Centerlines``."""

    paths: dict[str, np.ndarray]
    bifurcation_node: int | None
    info: dict = field(default_factory=dict)
    terminal: dict[str, tuple[bool, ...]] = field(default_factory=dict)

    def open_ends(self) -> dict[str, tuple[bool, ...]]:
        """For each path with open ends, which: True for its first point, False for its last."""
        return self.terminal


def _median_radius(points: np.ndarray, radius_at, skip_start: float = 0.0) -> float:
    """Median radius over a path (n, 3), skipping the first ``skip_start`` mm if enough remains."""
    s = arclength(points)
    keep = s >= min(skip_start, 0.5 * s[-1])
    return float(np.median(radius_at(points[keep])))


def _direction(points: np.ndarray, length: float) -> np.ndarray:
    """Unit vector from the first point to the point ``length`` mm along the path."""
    s = arclength(points)
    k = min(int(np.searchsorted(s, length)), len(points) - 1)
    d = points[k] - points[0]
    return d / max(np.linalg.norm(d), 1e-12)


def _choose_inlet(graph: Graph, radius_at) -> tuple[int, dict]:
    """The open end of the CCA and the score of every open end."""
    deg = graph.degree()
    terminals = np.flatnonzero(deg == 1)
    r_nodes = radius_at(graph.nodes)
    thick, oppose = {}, {}
    for t in terminals:
        e = graph.edges[graph.incident(t)[0]]
        j = e.other(t)
        from_end = e.from_node(t)
        near = arclength(from_end) <= 4.0 * r_nodes[t]
        thick[t] = float(np.median(radius_at(from_end[near] if near.sum() >= 3 else from_end)))
        others = [graph.edges[k] for k in graph.incident(j) if graph.edges[k] is not e]
        if others:
            reach = 2.0 * r_nodes[j]
            mine = _direction(e.from_node(j), reach)
            oppose[t] = -float(np.mean([mine @ _direction(f.from_node(j), reach) for f in others]))
        else:
            oppose[t] = 0.0
    lowest = terminals[np.argmin(graph.nodes[terminals, 2])]
    top = max(thick.values())
    score = {int(t): thick[t] / top + 0.5 * oppose[t] + 0.25 * (t == lowest) for t in terminals}
    inlet = max(score, key=score.get)
    return inlet, {"inlet_scores": {str(k): round(v, 3) for k, v in score.items()}}


def _follow(graph: Graph, start: int, via: int, radius_at, used: set[int]) -> tuple[list[int], list[int]]:
    """Follow edge ``via`` from node ``start`` to an open end, taking the thickest, best-aligned child at each
    junction.  Returns the node sequence and the edge sequence; the edges are added to ``used``."""
    nodes, edges = [start], []
    while True:
        e = graph.edges[via]
        used.add(via)
        edges.append(via)
        node = e.other(nodes[-1])
        nodes.append(node)
        children = [k for k in graph.incident(node) if k not in used]
        if not children:
            return nodes, edges
        incoming = -_direction(e.from_node(node), 2.0 * float(radius_at(graph.nodes[[node]])[0]))
        score = [_median_radius(graph.edges[k].from_node(node), radius_at)
                 + 0.5 * float(incoming @ _direction(graph.edges[k].from_node(node), 5.0)) for k in children]
        via = children[int(np.argmax(score))]


def _path_points(graph: Graph, nodes: list[int], edges: list[int]) -> np.ndarray:
    """The concatenated points of consecutive edges, from ``nodes[0]``."""
    parts = [graph.edges[e].from_node(n) for n, e in zip(nodes[:-1], edges)]
    return np.concatenate([parts[0]] + [p[1:] for p in parts[1:]])


def label_tree(graph: Graph, radius_at, anatomical_frame: bool = True) -> Labelled:
    """Name the branches of a pruned skeleton graph.

    Parameters
    ----------
    graph : Graph
        Pruned and simplified (see ``graph.simplify``); a tree with at least one edge.
    radius_at : callable
        Inscribed-sphere radius (mm) at points (n, 3) mm.
    anatomical_frame : bool
        Whether world z may be taken as superior (true for an image in LPS); the posterior cue is only
        used if, in addition, the CCA found runs up the z axis.

    Returns
    -------
    Labelled
    """
    inlet, info = _choose_inlet(graph, radius_at)
    used: set[int] = set()
    r_nodes = radius_at(graph.nodes)
    # Walk down the trunk to the first junction with two comparable children.
    trunk_nodes, trunk_edges = [inlet], []
    via = graph.incident(inlet)[0]
    bif = None
    while True:
        used.add(via)
        trunk_edges.append(via)
        node = graph.edges[via].other(trunk_nodes[-1])
        trunk_nodes.append(node)
        children = [k for k in graph.incident(node) if k not in used]
        if not children:
            break
        size = {k: _median_radius(graph.edges[k].from_node(node), radius_at, 1.5 * r_nodes[node]) for k in children}
        ranked = sorted(children, key=size.get, reverse=True)
        if len(ranked) >= 2 and size[ranked[1]] >= DAUGHTER_FRACTION * size[ranked[0]]:
            bif = node
            break
        via = ranked[0]
    paths = {"CCA": _path_points(graph, trunk_nodes, trunk_edges)}
    if bif is not None:
        daughters = []
        for k in ranked[:2]:
            nodes, edges = _follow(graph, bif, k, radius_at, used)
            daughters.append((_path_points(graph, nodes, edges), len(nodes) - 2))
        ica, votes = _ica_votes(daughters, paths["CCA"], radius_at, float(r_nodes[bif]), anatomical_frame)
        paths["ICA"] = daughters[ica][0]
        paths["ECA"] = daughters[1 - ica][0]
        info["ica_votes"] = votes
    info["branches_in_graph"] = len(graph.edges)
    terminal = {"CCA": (True,), "ICA": (False,), "ECA": (False,)} if bif is not None else {}
    if bif is None:  # the trunk ends at a second open end (or at a junction of minor branches only)
        terminal["CCA"] = (True, False) if graph.degree()[trunk_nodes[-1]] == 1 else (True,)
    _side_branches(graph, inlet, used, paths, terminal)
    return Labelled(paths, bif, info, terminal)


def _ica_votes(daughters, cca: np.ndarray, radius_at, r_bif: float, anatomical_frame: bool):
    """Index (0 or 1) of the ICA among two daughter paths, and the votes (positive: daughter 0 is the ICA)."""
    (p0, n0), (p1, n1) = daughters

    def window_mean(p):
        s = arclength(p)
        keep = (s >= r_bif) & (s <= 3.0 * r_bif)
        return float(np.mean(radius_at(p[keep] if keep.any() else p)))

    votes = {"bulb": int(np.sign(window_mean(p0) - window_mean(p1))),
             "fewer_side_branches": int(np.sign(n1 - n0)),
             "larger_median_radius": int(np.sign(_median_radius(p0, radius_at, r_bif)
                                                  - _median_radius(p1, radius_at, r_bif)))}
    up = _direction(cca[::-1], 20.0) @ np.array([0.0, 0.0, -1.0])  # CCA direction inlet -> bifurcation
    if anatomical_frame and up > 0.7:
        votes["posterior"] = int(np.sign(_direction(p0, 15.0)[1] - _direction(p1, 15.0)[1]))
    total = sum(votes.values())
    first_is_ica = total > 0 or (total == 0 and votes["bulb"] >= 0)
    return (0 if first_is_ica else 1), votes


def _side_branches(graph: Graph, inlet: int, used: set[int], paths: dict, terminal: dict) -> None:
    """Add every edge not yet named as ``branch<k>``, oriented away from the inlet (in place)."""
    depth = {inlet: 0}
    frontier = [inlet]
    while frontier:  # breadth-first over the (small) node graph
        nxt = []
        for n in frontier:
            for k in graph.incident(n):
                m = graph.edges[k].other(n)
                if m not in depth:
                    depth[m] = depth[n] + 1
                    nxt.append(m)
        frontier = nxt
    rest: list[Edge] = [e for k, e in enumerate(graph.edges) if k not in used]
    rest.sort(key=lambda e: -e.length)
    deg = graph.degree()
    for k, e in enumerate(rest, start=1):
        start = e.a if depth.get(e.a, 0) <= depth.get(e.b, 0) else e.b
        paths[f"branch{k}"] = e.from_node(start)
        if deg[e.other(start)] == 1:
            terminal[f"branch{k}"] = (False,)


def _fit_line(points: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Least-squares line (centroid, unit direction along the path) through the points between arc lengths
    ``lo`` and ``hi`` mm; None if fewer than 3 points lie there."""
    s = arclength(points)
    sel = points[(s >= lo) & (s <= hi)]
    if len(sel) < 3:
        return None
    c = sel.mean(axis=0)
    u = np.linalg.svd(sel - c)[2][0]
    return c, (u if u @ (points[-1] - points[0]) >= 0 else -u)


def bifurcation_point(cca: np.ndarray, ica: np.ndarray, eca: np.ndarray, r_junction: float) -> np.ndarray | None:
    """Where the daughter axes, extended back, branch off the CCA axis.

    Thinning puts the junction of a Y where the maximal sphere touches the flow divider, about two
    thirds of a radius downstream of where the daughter axes actually leave the trunk (the phantom's
    definition of the bifurcation: the point where its three axis splines meet).  The daughters are
    straight and well centred from half a junction radius to two junction radii beyond the junction, so
    each is fitted by a line there and the point of the CCA axis line (fitted over one to four radii
    upstream) closest to it is found; the bifurcation is the mean of the two.

    Parameters
    ----------
    cca : ndarray, shape (n, 3)
        CCA axis from inlet to the junction, mm.
    ica, eca : ndarray, shape (m, 3)
        Daughter axes from the junction outward, mm.
    r_junction : float
        Inscribed radius at the junction, mm.

    Returns
    -------
    ndarray, shape (3,), or None
        None if an axis is too short, a daughter runs nearly parallel to the trunk, or the point found is
        more than two junction radii from the junction.
    """
    trunk = _fit_line(cca[::-1], r_junction, 4.0 * r_junction)
    found = []
    for d in (ica, eca):
        line = _fit_line(d, 0.5 * r_junction, 2.0 * r_junction)
        if trunk is None or line is None:
            return None
        (c1, u1), (c2, u2) = trunk, line
        cross = 1.0 - (u1 @ u2) ** 2
        if cross < np.sin(np.deg2rad(10.0)) ** 2:
            return None
        w = c1 - c2
        t = ((u1 @ u2) * (u2 @ w) - (u1 @ w)) / cross
        found.append(c1 + t * u1)
    point = np.mean(found, axis=0)
    return point if np.linalg.norm(point - cca[-1]) <= 2.0 * r_junction else None


def splice_at(point: np.ndarray, cca: np.ndarray, daughters: list[np.ndarray], skip: float):
    """Re-join the CCA and its daughters at ``point``: the CCA is cut at its nearest point to ``point`` and
    ends there; each daughter starts at ``point`` and joins its own axis ``skip`` mm from its start.

    Returns
    -------
    cca : ndarray, shape (n', 3)
    daughters : list of ndarray
    """
    k = max(int(np.argmin(np.linalg.norm(cca - point, axis=1))), 1)
    new_cca = np.concatenate([cca[:k], point[None]])
    out = []
    for d in daughters:
        s = arclength(d)
        out.append(np.concatenate([point[None], d[s >= min(skip, 0.5 * s[-1])]]))
    return new_cca, out
