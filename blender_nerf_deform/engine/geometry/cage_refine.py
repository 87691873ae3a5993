"""Refining a built cage: longest-edge bisection where a pose needs more freedom.

The cage is tetrahedralized once (cage.py); this module only splits its tets, so
the boundary surface, the original vertices' indices and every tet's positive
orientation are kept. Two uses: a finer band where a pose will stretch (Build
Cage's Refine Selected, `cage --refine-edge`), and `separate_regions`, which
splits the tets around the cage vertices that two regions (handles, the pinned
region) both lean on, so that no cage vertex has to follow two transforms.

PURE NUMPY on purpose: the add-on refines the stored cage in Blender's own
Python when a handle is added (tools/check_layering.py enforces it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import EngineError
from .barycentric import tet_inverses

_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def median_edge(vertices: np.ndarray, tets: np.ndarray) -> float:
    """The median length of the tets' edges (each edge counted once per tet holding it)."""
    V, T = np.asarray(vertices, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    return float(np.median(np.linalg.norm(V[T[:, _TET_EDGES[:, 0]]] - V[T[:, _TET_EDGES[:, 1]]], axis=-1)))


@dataclass(frozen=True)
class Bisection:
    """What a refinement did, so that data attached to the old cage can follow it."""

    vertices: np.ndarray  # (N', 3): the old vertices first, then the new edge midpoints
    tets: np.ndarray  # (M', 4)
    tet_parent: np.ndarray  # (M',) the old tet each new tet lies in
    vertex_parents: np.ndarray  # (N' - N, 2): the edge each new vertex halves (earlier vertices)
    pass_starts: np.ndarray  # index of the first new vertex of each pass (a pass's parents precede it)

    def extend_values(self, values: np.ndarray) -> np.ndarray:
        """Per-vertex values of the old cage (N, ...) carried to the refined one: each new vertex
        takes the mean of its edge's two ends (linear along the edge, as the cage's map is)."""
        values = np.asarray(values, dtype=np.float64)
        n_old = len(self.vertices) - len(self.vertex_parents)
        out = np.empty((len(self.vertices),) + values.shape[1:])
        out[:n_old] = values
        for start, stop in zip(self.pass_starts, list(self.pass_starts[1:]) + [len(self.vertices)]):
            ends = self.vertex_parents[start - n_old : stop - n_old]
            out[start:stop] = 0.5 * (out[ends[:, 0]] + out[ends[:, 1]])
        return out


def _check_box(box) -> np.ndarray | None:
    if box is None:
        return None
    box = np.asarray(box, dtype=np.float64)
    if (
        box.ndim not in (2, 3)
        or box.shape[-2:] != (2, 3)
        or not np.isfinite(box).all()
        or not (box[..., 1, :] >= box[..., 0, :]).all()
    ):
        raise EngineError(f"cage refinement box must be (lo xyz, hi xyz) with hi >= lo, got {box.tolist()}")
    return box.reshape(-1, 2, 3)


def bisect(vertices: np.ndarray, tets: np.ndarray, max_edge: float, box=None, max_passes: int = 64) -> Bisection:
    """Longest-edge bisection of the tets (whose centroid lies inside `box`: a (2, 3) lo/hi, or
    (K, 2, 3) for several boxes; or everywhere) whose longest edge exceeds `max_edge`.

    Rivara's longest-edge bisection, conforming: a tet is only ever split at its own longest edge
    (a neighbour around that edge is split first at its own, as often as needed), an edge is split
    in all its tets at once, so the boundary surface is unchanged (new boundary vertices lie on its
    faces), tets keep their shape (no needles: each split halves the longest edge), every tet keeps
    a positive volume, and the original vertices keep their indices (new ones are appended)."""
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(tets, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4 or len(T) == 0:
        raise EngineError(f"refine_cage: need (N,3) vertices and (M,4) tets, got {V.shape} and {T.shape}")
    if not np.isfinite(V).all() or T.min() < 0 or T.max() >= len(V):
        raise EngineError("refine_cage: vertices must be finite and tets index them")
    if not (
        isinstance(max_edge, (int, float)) and not isinstance(max_edge, bool) and np.isfinite(max_edge) and max_edge > 0
    ):
        raise EngineError(f"cage refinement edge length must be a positive number, got {max_edge!r}")
    boxes = _check_box(box)
    parent = np.arange(len(T))
    parts, vertex_parents, pass_starts = [V], [np.zeros((0, 2), dtype=np.int64)], []
    for _ in range(max_passes):
        allv = parts[0] if len(parts) == 1 else np.concatenate(parts)
        parts = [allv]
        pairs = np.sort(T[:, _TET_EDGES], axis=2)  # (M, 6, 2)
        length = np.linalg.norm(allv[pairs[..., 0]] - allv[pairs[..., 1]], axis=2)  # (M, 6)
        edges, inverse = np.unique(pairs.reshape(-1, 2), axis=0, return_inverse=True)
        inverse = inverse.reshape(len(T), 6)
        # Each tet's longest edge, ties broken alike in every tet (by edge id), so that a tet is only
        # ever split at its own longest edge: splitting a neighbour at a shorter edge breeds needles
        # (midpoints creeping towards a third of an edge never split) that never end.
        elen = np.zeros(len(edges))
        elen[inverse.ravel()] = length.ravel()
        order = np.lexsort((np.arange(len(edges)), -elen))
        rank = np.empty(len(edges), dtype=np.int64)
        rank[order] = np.arange(len(edges))
        local = rank[inverse].argmin(axis=1)
        longest = inverse[np.arange(len(T)), local]  # (M,) edge ids
        todo = elen[longest] > max_edge
        if boxes is not None:
            c = allv[T].mean(axis=1)
            inside = np.zeros(len(T), dtype=bool)
            for lo, hi in boxes:
                inside |= ((c >= lo) & (c <= hi)).all(axis=1)
            todo &= inside
        if not todo.any():
            break
        # Rivara's closure: a tet around an edge to split is split too, at its own longest edge first.
        marked = np.zeros(len(edges), dtype=bool)
        marked[longest[todo]] = True
        while True:
            around = marked[inverse].any(axis=1)
            if not (around & ~todo).any():
                break
            todo |= around
            marked[longest[todo]] = True
        # Split now: the marked edges that are the longest of every tet around them.
        split = marked.copy()
        np.logical_and.at(split, inverse.ravel(), (~marked[inverse] | (longest[:, None] == inverse)).ravel())
        new_id = np.full(len(edges), -1, dtype=np.int64)
        new_id[split] = len(allv) + np.arange(int(split.sum()))
        pass_starts.append(len(allv))
        parts.append(0.5 * (allv[edges[split, 0]] + allv[edges[split, 1]]))
        vertex_parents.append(edges[split])
        cut = split[longest]  # a tet holds at most one split edge: its longest
        t_cut, loc = T[cut], _TET_EDGES[local[cut]]
        mid = new_id[inverse[cut, local[cut]]]
        rows = np.arange(len(t_cut))
        a, b = t_cut.copy(), t_cut.copy()
        a[rows, loc[:, 1]] = mid  # (.., m in place of the edge's second vertex)
        b[rows, loc[:, 0]] = mid  # (.., m in place of its first)
        T = np.concatenate([T[~cut], a, b])
        parent = np.concatenate([parent[~cut], parent[cut], parent[cut]])
    else:
        raise EngineError(
            f"cage refinement did not finish in {max_passes} passes (max edge {max_edge:g} too small for the cage)"
        )
    allv = parts[0] if len(parts) == 1 else np.concatenate(parts)
    return Bisection(
        allv, T, parent, np.concatenate(vertex_parents).astype(np.int64), np.asarray(pass_starts, dtype=np.int64)
    )


def refine_cage(
    vertices: np.ndarray, tets: np.ndarray, max_edge: float, box=None, max_passes: int = 64
) -> tuple[np.ndarray, np.ndarray]:
    """A finer cage where a pose will vary fast: `bisect`'s (vertices, tets).

    A ray-bent frame is the piecewise-affine map of the cage, so where a pose's deformation
    gradient changes within a tet (a smooth stretch across a band narrower than a few tets) the
    surface lands off its place and smears; the cage is built once for all frames, so it is
    refined at build time, where the user will stretch."""
    b = bisect(vertices, tets, max_edge, box, max_passes)
    return b.vertices, b.tets


def selection_box(points: np.ndarray, margin: float, max_edge: float) -> np.ndarray:
    """The (2, 3) box of `points` (the surface vertices the user will stretch) widened by the cage's
    `margin` and the edge length, so the tets wrapping them are refined too."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0:
        raise EngineError("cage refinement around a selection: no vertices are selected")
    if not np.isfinite(P).all():
        raise EngineError("cage refinement around a selection: the selected vertices are not finite")
    pad = float(margin) + float(max_edge)
    return np.stack([P.min(axis=0) - pad, P.max(axis=0) + pad])


def refine_around(
    vertices: np.ndarray, tets: np.ndarray, points: np.ndarray, margin: float, max_edge: float | None = None
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """`refine_cage` in the `selection_box` of `points`. `max_edge` None: half the cage's median tet
    edge (a smooth stretch across a band needs a few tets across it; half the as-built size brings a
    stretch to the exact map's quality). Returns (vertices, tets, the edge length used, the box)."""
    V, T = np.asarray(vertices, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    if max_edge is None:
        max_edge = 0.5 * median_edge(V, T)
    box = selection_box(points, margin, max_edge)
    V2, T2 = refine_cage(V, T, float(max_edge), box)
    return V2, T2, float(max_edge), box


def extend_vertex_labels(labels: np.ndarray, tets: np.ndarray, n_vertices: int) -> np.ndarray:
    """Per-vertex labels (a cage's part per vertex) for a refined cage: its first len(labels)
    vertices keep theirs, each new one takes a labelled neighbour's in a tet (no tet joins two
    parts, so every vertex of a tet has the same part)."""
    out = np.full(n_vertices, -1, dtype=np.int64)
    out[: len(labels)] = labels
    T = np.asarray(tets, dtype=np.int64)
    for _ in range(64):
        missing = out[T] < 0
        if not missing.any():
            return out
        known = out[T].max(axis=1)  # a tet's part (-1 while none of its vertices is labelled)
        rows = (missing & (known[:, None] >= 0)).nonzero()
        out[T[rows]] = known[rows[0]]
    raise EngineError("refined cage: some new vertices lie in no tet with a labelled vertex")


# Where two regions meet: pad around each shared cage vertex and the longest edge left there, in
# median edges of the cage as built (chosen on the demo's cages: the smallest that bring the handles'
# surface close to its targets; larger ones left it visibly off).
SEPARATION_PAD = 1.0
SEPARATION_EDGE = 0.6


def leaned_on(tets: np.ndarray, tet_ids: np.ndarray, weights: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The cage vertices (sorted) whose positions move any of the embedded `points`."""
    points = np.asarray(points, dtype=np.int64)
    corners = np.asarray(tets, dtype=np.int64)[np.asarray(tet_ids, dtype=np.int64)[points]]
    return np.unique(corners[np.abs(np.asarray(weights)[points]) > 1e-9])


def _region_vertices(tets, tet_ids, weights, handles, pinned_points, cage_pins) -> list[np.ndarray]:
    """The cage vertices each region leans on: one set per handle, then one for the still ones (the
    pinned surface vertices and the cage vertices pinned at a cut hold the same transform, so they
    never conflict with each other), when there are any."""
    sets = [leaned_on(tets, tet_ids, weights, h) for h in handles]
    still = np.zeros(0, dtype=np.int64)
    if pinned_points is not None and len(pinned_points):
        still = leaned_on(tets, tet_ids, weights, pinned_points)
    if cage_pins is not None and len(cage_pins):
        still = np.union1d(still, np.asarray(cage_pins, dtype=np.int64))
    return sets + [still] if len(still) else sets


def _shared_by_pairs(sets: list[np.ndarray]) -> dict[tuple[int, int], np.ndarray]:
    out = {}
    for i in range(len(sets)):
        for j in range(i + 1, len(sets)):
            common = np.intersect1d(sets[i], sets[j])
            if len(common):
                out[(i, j)] = common
    return out


def shared_vertices(
    tets: np.ndarray, tet_ids: np.ndarray, weights: np.ndarray, handles: list, pinned_points=None, cage_pins=None
) -> np.ndarray:
    """The cage vertices (sorted) that two regions lean on: two handles' (surface vertex indices), or
    a handle's and the still ones' (the pinned surface vertices and the cut's pinned cage vertices)."""
    pairs = _shared_by_pairs(_region_vertices(tets, tet_ids, weights, handles, pinned_points, cage_pins))
    return np.unique(np.concatenate(list(pairs.values()))) if pairs else np.zeros(0, dtype=np.int64)


@dataclass(frozen=True)
class Separation:
    """A cage refined where regions met, with the surface's embedding and the cut's pins moved onto
    it. Pairs name regions by index: 0..len(handles)-1 the handles, len(handles) the still ones."""

    bisection: Bisection | None  # None: no pair could be parted, the cage stays as it was
    tet_ids: np.ndarray | None  # (P,) each surface vertex's tet in the refined cage
    weights: np.ndarray | None  # (P, 4) its barycentric weights there (the same rest position)
    cage_pins: np.ndarray | None  # the cut's pins: the old ones and the midpoints of edges between two of them
    parted: list  # pairs of regions that shared cage vertices and no longer do
    too_close: list  # pairs closer than the refined tets: left as built (refining would not part them)
    edge: float  # the longest edge left around the shared vertices

    @property
    def vertices(self) -> np.ndarray:
        return self.bisection.vertices

    @property
    def tets(self) -> np.ndarray:
        return self.bisection.tets


def reembed(
    bisection: Bisection, old_tets: np.ndarray, old_vertices: np.ndarray, tet_ids: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The embedding of points in the refined cage: the same rest positions, each point in one of
    the tets its old tet was split into (so a multi-part cage's points stay in their own part);
    points of tets left whole keep their weights exactly."""
    tet_ids = np.asarray(tet_ids, dtype=np.int64)
    weights = np.asarray(weights, dtype=np.float64)
    order = np.argsort(bisection.tet_parent, kind="stable")
    n_children = np.bincount(bisection.tet_parent, minlength=len(old_tets))
    first = np.cumsum(n_children) - n_children
    new_ids = order[first[tet_ids]].copy()
    new_weights = weights.copy()
    moved = np.flatnonzero(n_children[tet_ids] > 1)
    if not len(moved):
        return new_ids, new_weights
    rest = np.einsum("nk,nkc->nc", weights[moved], np.asarray(old_vertices)[np.asarray(old_tets)[tet_ids[moved]]])
    inverses = tet_inverses(bisection.vertices, bisection.tets)
    best = np.full(len(moved), -np.inf)
    for r in range(int(n_children[tet_ids[moved]].max())):
        has = n_children[tet_ids[moved]] > r
        rows = moved[has]
        child = order[first[tet_ids[rows]] + r]
        G = inverses[child]
        lam = np.einsum("nij,nj->ni", G[:, :, :3], rest[has]) + G[:, :, 3]
        better = lam.min(axis=1) > best[has]  # inside: min >= 0; outside the cage: the least outside
        idx = np.flatnonzero(has)[better]
        best[idx] = lam[better].min(axis=1)
        new_ids[rows[better]], new_weights[rows[better]] = child[better], lam[better]
    return new_ids, new_weights


def _refined(V, T, tet_ids, weights, max_edge, shared, pad_length, cage_pins):
    boxes = np.stack([V[shared] - pad_length, V[shared] + pad_length], axis=1)
    bisection = bisect(V, T, max_edge, boxes)
    new_ids, new_weights = reembed(bisection, T, V, tet_ids, weights)
    pinned = np.zeros(len(V))
    pinned[cage_pins] = 1.0
    new_pins = np.flatnonzero(bisection.extend_values(pinned) == 1.0)
    return bisection, new_ids, new_weights, new_pins


def separate_regions(
    vertices: np.ndarray,
    tets: np.ndarray,
    tet_ids: np.ndarray,
    weights: np.ndarray,
    handles: list,
    pinned_points=None,
    cage_pins=None,
    pad: float = SEPARATION_PAD,
    edge: float = SEPARATION_EDGE,
) -> Separation | None:
    """Refine the cage around the cage vertices that two regions lean on, so that each region's
    surface can follow its own transform: a vertex shared by two handles' tets must serve both, and
    a fold-free solve then leaves the surface off its targets (by a few percent of the region's size
    on coarse cages). Tets whose centroid lies within `pad` median edges of a shared
    vertex are bisected down to `edge` median edges. Each pair of regions is tried on its own first:
    a pair closer than the refined tets would stay shared however many tets it got, so it is left
    as built (`too_close`) and does not cost the others their refinement. None when no cage vertex
    is shared (nothing to do)."""
    V, T = np.asarray(vertices, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    cage_pins = np.zeros(0, dtype=np.int64) if cage_pins is None else np.asarray(cage_pins, dtype=np.int64)
    pairs = _shared_by_pairs(_region_vertices(T, tet_ids, weights, handles, pinned_points, cage_pins))
    if not pairs:
        return None
    step = median_edge(V, T)
    max_edge, pad_length = edge * step, pad * step
    parted, too_close = [], []
    for (i, j), shared in pairs.items():
        trial = _refined(V, T, tet_ids, weights, max_edge, shared, pad_length, cage_pins)
        sets = _region_vertices(trial[0].tets, trial[1], trial[2], handles, pinned_points, trial[3])
        (parted if not len(np.intersect1d(sets[i], sets[j])) else too_close).append((i, j))
    if not parted:
        return Separation(None, None, None, None, [], too_close, max_edge)
    if len(pairs) > 1:  # the parted pairs' refinements together (a lone pair's trial is the result)
        shared = np.unique(np.concatenate([pairs[pair] for pair in parted]))
        trial = _refined(V, T, tet_ids, weights, max_edge, shared, pad_length, cage_pins)
    return Separation(*trial, parted, too_close, max_edge)
