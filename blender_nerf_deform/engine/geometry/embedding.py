"""Surface embedding: each vertex of the extracted mesh as (tet, 4 weights) in the rest cage.

The deformed surface is then `weights · deformed cage vertices` (a sparse
linear map), which the Blender add-on evaluates on every handle move for the
live preview. PURE NUMPY on purpose: the add-on imports this module and never
torch (tools/check_layering.py enforces it), so this file has its own small
vectorised grid locator instead of `locate.py`'s torch/numba one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import EngineError
from .barycentric import as_tets, tet_inverses


@dataclass(frozen=True)
class Embedding:
    """`corners` (N,4) cage vertex indices and `weights` (N,4) barycentric weights per embedded point."""

    tet_ids: np.ndarray  # (N,) containing tet (nearest one for points outside the cage)
    corners: np.ndarray  # (N, 4) int64: tets[tet_ids]
    weights: np.ndarray  # (N, 4) float64, rows sum to 1
    n_outside: int  # points not inside any tet (weights extrapolate the nearest tet's affine map)

    def apply(self, deformed_vertices: np.ndarray) -> np.ndarray:
        """(N, 3) positions of the embedded points for the given cage vertex positions."""
        V = np.asarray(deformed_vertices, dtype=np.float64)
        return np.einsum("nk,nkc->nc", self.weights, V[self.corners])

    def cage_vertex_weights(self, point_indices: np.ndarray, n_cage_vertices: int) -> np.ndarray:
        """(n_cage_vertices,) total barycentric weight the given points put on each cage vertex."""
        idx = np.asarray(point_indices, dtype=np.int64)
        return np.bincount(self.corners[idx].ravel(), weights=self.weights[idx].ravel(), minlength=n_cage_vertices)


def locate(
    points: np.ndarray,
    vertices: np.ndarray,
    tets: np.ndarray,
    cells_per_tet: float = 1.0,
    eps: float = 1e-10,
    chunk: int = 1 << 18,
) -> tuple[np.ndarray, np.ndarray]:
    """(tet index or -1, (N,4) barycentric coords) of each point: uniform grid of tet lists, numpy only."""
    V, T = as_tets(vertices, tets)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    inv = tet_inverses(V, T)  # (M,4,4)
    if not np.isfinite(inv).all():
        raise EngineError("degenerate cage: some tets have zero volume")
    C = V[T]
    tlo, thi = C.min(1), C.max(1)
    lo = V.min(0)
    extent = np.maximum(V.max(0) - lo, 1e-12)
    h = (extent.prod() / (cells_per_tet * len(T))) ** (1 / 3)
    res = np.clip(np.ceil(extent / h), 1, 512).astype(np.int64)
    scale = res / extent
    i0 = np.clip(np.floor((tlo - lo) * scale).astype(np.int64), 0, res - 1)
    i1 = np.clip(np.floor((thi - lo) * scale).astype(np.int64), 0, res - 1)
    span = i1 - i0 + 1
    n = span.prod(1)
    owner = np.repeat(np.arange(len(T)), n)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(n) - n, n)
    s = span[owner]
    ijk = i0[owner] + np.stack([k % s[:, 0], (k // s[:, 0]) % s[:, 1], k // (s[:, 0] * s[:, 1])], axis=1)
    # Drop pairs whose cell lies wholly outside one of the tet's face planes.
    half = 0.5 / scale
    centre = lo + (ijk + 0.5) / scale
    G = inv[owner]
    lam = np.einsum("nij,nj->ni", G[:, :, :3], centre) + G[:, :, 3]
    reach = np.abs(G[:, :, :3]) @ half
    keep = (lam + reach).min(1) >= -eps
    cell = (ijk[keep, 2] * res[1] + ijk[keep, 1]) * res[0] + ijk[keep, 0]
    owner = owner[keep]
    order = np.argsort(cell, kind="stable")
    cell_tets = owner[order]
    counts = np.bincount(cell, minlength=int(res.prod()))
    starts = np.cumsum(counts) - counts

    out = np.full(len(P), -1, dtype=np.int64)
    bary = np.zeros((len(P), 4))
    for s0 in range(0, len(P), chunk):
        p = P[s0 : s0 + chunk]
        f = (p - lo) * scale
        ok = np.all((f >= 0) & (f <= res), axis=1)
        ijk = np.minimum(np.floor(f).astype(np.int64), res - 1)
        cid = (ijk[:, 2] * res[1] + ijk[:, 1]) * res[0] + ijk[:, 0]
        active = np.flatnonzero(ok)
        active = active[counts[cid[active]] > 0]
        start, count = starts[cid[active]], counts[cid[active]]
        r = 0
        while len(active):
            t = cell_tets[start + r]
            G = inv[t]
            lam = np.einsum("nij,nj->ni", G[:, :, :3], p[active]) + G[:, :, 3]
            hit = lam.min(1) >= -eps
            out[s0 + active[hit]] = t[hit]
            bary[s0 + active[hit]] = lam[hit]
            r += 1
            more = ~hit & (count > r)
            active, start, count = active[more], start[more], count[more]
    return out, bary


def embed_points(points: np.ndarray, rest_vertices: np.ndarray, tets: np.ndarray) -> Embedding:
    """Embed points (the extracted mesh's vertices) in the rest cage.

    Points outside every tet (there should be none when the cage was built
    around this mesh with a margin) are attached to the tet with the nearest
    centroid, with barycentric weights that extrapolate its affine map, and
    counted in `n_outside`.
    """
    V, T = as_tets(rest_vertices, tets)
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise EngineError(f"points to embed must have shape (N, 3), got {P.shape}")
    tid, w = locate(P, V, T)
    missing = np.flatnonzero(tid < 0)
    if len(missing):
        cent = V[T].mean(1)
        inv = tet_inverses(V, T)
        near = np.empty(len(missing), dtype=np.int64)
        for s in range(0, len(missing), 4096):
            q = P[missing[s : s + 4096]]
            d = (q * q).sum(1)[:, None] - 2 * q @ cent.T + (cent * cent).sum(1)[None]
            near[s : s + 4096] = d.argmin(1)
        tid[missing] = near
        G = inv[near]
        w[missing] = np.einsum("nij,nj->ni", G[:, :, :3], P[missing]) + G[:, :, 3]
    return Embedding(tet_ids=tid, corners=T[tid], weights=w, n_outside=int(len(missing)))


def embed_points_by_part(
    points: np.ndarray, point_part: np.ndarray, rest_vertices: np.ndarray, tets: np.ndarray, vertex_part: np.ndarray
) -> Embedding:
    """Embed each part's points in that part's own cage only (cage.build_part_cages): where two
    objects' cages meet, a point of one is never attached to the other's tets."""
    V, T = as_tets(rest_vertices, tets)
    P = np.asarray(points, dtype=np.float64)
    tet_part = np.asarray(vertex_part)[T[:, 0]]
    tid = np.empty(len(P), dtype=np.int64)
    w = np.empty((len(P), 4))
    outside = 0
    for i in np.unique(point_part):
        pts, own = np.flatnonzero(point_part == i), np.flatnonzero(tet_part == i)
        if len(own) == 0:
            raise EngineError(f"part {i + 1} of the mesh has no cage of its own")
        e = embed_points(P[pts], V, T[own])
        tid[pts], w[pts] = own[e.tet_ids], e.weights
        outside += e.n_outside
    return Embedding(tet_ids=tid, corners=T[tid], weights=w, n_outside=outside)
