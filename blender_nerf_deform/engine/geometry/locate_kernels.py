"""Fused CPU kernels (numba) for point location in a tet cage: grid build and query.

Why: on CPU the torch formulation of `locate.py` spends its time in
materialised (pairs, 12) gathers and per-round compactions; on a laptop CPU it
runs at about igl's speed, not above it.
These kernels do the same uniform-grid method (cells list the tets that
overlap them, pruned by the tets' face planes) with the per-tet and per-point
work in registers. Build: one parallel pass over the tets (bounding-box cells,
pruned by the face planes, each kept (tet, cell) pair scored by the signed
distance from the cell's centre to the tet's nearest face plane, and counted
per thread and cell), a parallel counting sort of the pairs by cell, then each
cell's list sorted by score, best first. Query: parallel over points, testing
each point's candidates in that order until the first hit. Sorting the lists
is what makes the query fast: the tet that covers most of a cell comes first,
so a point inside the cage tests ~3.8 candidates instead of ~10 (52k-tet
fTetWild cage, `tools/bench/geometry_locate.py`). Always float64.

Used only for CPU tensors; CUDA takes the torch path, so the renderer runs the
same method everywhere. numba is optional (as for the hash-grid kernels): without
it the torch path runs on CPU too, only slower.
"""

from __future__ import annotations

import numpy as np

from .. import backend

if backend.HAVE_NUMBA:
    import numba

    from ..kernel_cache import njit, prange


if backend.HAVE_NUMBA:

    @njit(parallel=True, cache=True)
    def tet_rows(V, T, R, tlo, thi):
        """R[t] = rows 1..3 of T⁻¹ (3x4); tlo/thi = bounding box. Returns the number of degenerate tets."""
        M = T.shape[0]
        bad = np.zeros(M, np.int64)
        for t in prange(M):
            a0, a1, a2 = V[T[t, 0], 0], V[T[t, 0], 1], V[T[t, 0], 2]
            e = np.empty((3, 3))
            for j in range(3):
                for c in range(3):
                    e[j, c] = V[T[t, j + 1], c] - V[T[t, 0], c]
            # rows of D⁻¹ (D has columns e1, e2, e3) = cross products / det
            c23 = (
                e[1, 1] * e[2, 2] - e[1, 2] * e[2, 1],
                e[1, 2] * e[2, 0] - e[1, 0] * e[2, 2],
                e[1, 0] * e[2, 1] - e[1, 1] * e[2, 0],
            )
            c31 = (
                e[2, 1] * e[0, 2] - e[2, 2] * e[0, 1],
                e[2, 2] * e[0, 0] - e[2, 0] * e[0, 2],
                e[2, 0] * e[0, 1] - e[2, 1] * e[0, 0],
            )
            c12 = (
                e[0, 1] * e[1, 2] - e[0, 2] * e[1, 1],
                e[0, 2] * e[1, 0] - e[0, 0] * e[1, 2],
                e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0],
            )
            det = e[0, 0] * c23[0] + e[0, 1] * c23[1] + e[0, 2] * c23[2]
            if det == 0.0:
                bad[t] = 1
                det = 1.0
            rows = (c23, c31, c12)
            for r in range(3):
                x, y, z = rows[r][0] / det, rows[r][1] / det, rows[r][2] / det
                R[t, r, 0] = x
                R[t, r, 1] = y
                R[t, r, 2] = z
                R[t, r, 3] = -(x * a0 + y * a1 + z * a2)
            for c in range(3):
                lo = V[T[t, 0], c]
                hi = lo
                for j in range(1, 4):
                    v = V[T[t, j], c]
                    lo = min(lo, v)
                    hi = max(hi, v)
                tlo[t, c] = lo
                thi[t, c] = hi
        return bad.sum()

    @njit(inline="always")
    def _pair_score(R, t, gn, cx, cy, cz, hx, hy, hz, eps):
        """-inf if the box (centre c, half sizes h) lies wholly outside one face plane of tet t;
        else the signed distance from c to the tet's nearest face plane (positive inside),
        `gn` holding the inverse norms of the gradients of λ1, λ2, λ3, λ0."""
        s0 = 1.0
        r0x = 0.0
        r0y = 0.0
        r0z = 0.0
        score = np.inf
        for r in range(3):
            gx, gy, gz = R[t, r, 0], R[t, r, 1], R[t, r, 2]
            lam = gx * cx + gy * cy + gz * cz + R[t, r, 3]
            if lam + abs(gx) * hx + abs(gy) * hy + abs(gz) * hz < -eps:
                return -np.inf
            score = min(score, lam * gn[r])
            s0 -= lam
            r0x += gx
            r0y += gy
            r0z += gz
        if s0 + abs(r0x) * hx + abs(r0y) * hy + abs(r0z) * hz < -eps:
            return -np.inf
        return min(score, s0 * gn[3])

    @njit(inline="always")
    def _cell(g, res):
        """floor(g) clamped to the cells 0..res-1 in floating point, before the cast: a NaN or huge
        coordinate cannot turn into an index outside the grid (the cast of those is undefined)."""
        g = np.floor(g)
        if not g > 0.0:
            return 0
        if g > res - 1:
            return res - 1
        return int(g)

    @njit(inline="always")
    def _cell_range(tlo, thi, t, c, glo, inv, res):
        return _cell((tlo[t, c] - glo[c]) * inv[c], res[c]), _cell((thi[t, c] - glo[c]) * inv[c], res[c])

    @njit(parallel=True, cache=True)
    def bbox_counts(tlo, thi, glo, inv, res, counts):
        """Cells in each tet's bounding box: an upper bound of its pairs (the fill prunes some)."""
        for t in prange(tlo.shape[0]):
            n = 1
            for c in range(3):
                a, b = _cell_range(tlo, thi, t, c, glo, inv, res)
                n *= b - a + 1
            counts[t] = n

    @njit(parallel=True, cache=True)
    def fill_pairs(R, tlo, thi, glo, inv, res, eps, offsets, bounds, pair_cell, pair_key, hist):
        """(tet, cell) pairs of each tet's bounding-box cells: the cell (-1 where the face planes
        prune it) and its score; hist[p, cell] counts the kept pairs of the tets bounds[p]:bounds[p+1]."""
        hx, hy, hz = 0.5 / inv[0], 0.5 / inv[1], 0.5 / inv[2]
        rx, ry = res[0], res[1]
        for p in prange(bounds.shape[0] - 1):
            gn = np.empty(4)
            for t in range(bounds[p], bounds[p + 1]):
                sx = 0.0
                sy = 0.0
                sz = 0.0
                for r in range(3):
                    gn[r] = 1.0 / max(np.sqrt(R[t, r, 0] ** 2 + R[t, r, 1] ** 2 + R[t, r, 2] ** 2), 1e-300)
                    sx += R[t, r, 0]
                    sy += R[t, r, 1]
                    sz += R[t, r, 2]
                gn[3] = 1.0 / max(np.sqrt(sx * sx + sy * sy + sz * sz), 1e-300)
                x0, x1 = _cell_range(tlo, thi, t, 0, glo, inv, res)
                y0, y1 = _cell_range(tlo, thi, t, 1, glo, inv, res)
                z0, z1 = _cell_range(tlo, thi, t, 2, glo, inv, res)
                n = offsets[t]
                for k in range(z0, z1 + 1):
                    for j in range(y0, y1 + 1):
                        for i in range(x0, x1 + 1):
                            sc = _pair_score(
                                R,
                                t,
                                gn,
                                glo[0] + (i + 0.5) / inv[0],
                                glo[1] + (j + 0.5) / inv[1],
                                glo[2] + (k + 0.5) / inv[2],
                                hx,
                                hy,
                                hz,
                                eps,
                            )
                            if sc == -np.inf:
                                pair_cell[n] = -1  # pruned: the cell lies outside one of the tet's face planes
                            else:
                                c = (k * ry + j) * rx + i
                                pair_cell[n] = c
                                pair_key[n] = sc
                                hist[p, c] += 1
                            n += 1

    @njit(cache=True)
    def cell_offsets(hist, cell_start):
        """CSR starts of the cells, and hist[p, c] turned into the first slot of chunk p's tets in cell c."""
        P, C = hist.shape
        run = 0
        for c in range(C):
            cell_start[c] = run
            for p in range(P):
                h = hist[p, c]
                hist[p, c] = run
                run += h
        cell_start[C] = run

    @njit(parallel=True, cache=True)
    def scatter_pairs(pair_cell, pair_key, offsets, bounds, next_slot, cell_tets, cell_key):
        """Counting sort by cell, each chunk of tets into its own slots: within a cell, tets in index order."""
        for p in prange(bounds.shape[0] - 1):
            for t in range(bounds[p], bounds[p + 1]):
                for q in range(offsets[t], offsets[t + 1]):
                    c = pair_cell[q]
                    if c < 0:
                        continue
                    s = next_slot[p, c]
                    next_slot[p, c] = s + 1
                    cell_tets[s] = t
                    cell_key[s] = pair_key[q]

    @njit(parallel=True, cache=True)
    def sort_cells(cell_start, cell_tets, cell_key):
        """Each cell's tets by score, best first (stable insertion sort: ties stay in index order)."""
        for c in prange(cell_start.shape[0] - 1):
            a, b = cell_start[c], cell_start[c + 1]
            for i in range(a + 1, b):
                k = cell_key[i]
                t = cell_tets[i]
                j = i - 1
                while j >= a and cell_key[j] < k:
                    cell_key[j + 1] = cell_key[j]
                    cell_tets[j + 1] = cell_tets[j]
                    j -= 1
                cell_key[j + 1] = k
                cell_tets[j + 1] = t

    @njit(parallel=True, cache=True)
    def query(P, glo, inv, res, cell_start, cell_tets, R, eps, out, bary, want_bary):
        N = P.shape[0]
        rx, ry, rz = res[0], res[1], res[2]
        for n in prange(N):
            out[n] = -1
            x, y, z = P[n, 0], P[n, 1], P[n, 2]
            fx, fy, fz = (x - glo[0]) * inv[0], (y - glo[1]) * inv[1], (z - glo[2]) * inv[2]
            if not (fx >= 0 and fy >= 0 and fz >= 0 and fx <= rx and fy <= ry and fz <= rz):
                continue
            i, j, k = min(int(fx), rx - 1), min(int(fy), ry - 1), min(int(fz), rz - 1)
            c = (k * ry + j) * rx + i
            for q in range(cell_start[c], cell_start[c + 1]):
                t = cell_tets[q]
                l1 = R[t, 0, 0] * x + R[t, 0, 1] * y + R[t, 0, 2] * z + R[t, 0, 3]
                if l1 < -eps:
                    continue
                l2 = R[t, 1, 0] * x + R[t, 1, 1] * y + R[t, 1, 2] * z + R[t, 1, 3]
                if l2 < -eps:
                    continue
                l3 = R[t, 2, 0] * x + R[t, 2, 1] * y + R[t, 2, 2] * z + R[t, 2, 3]
                if l3 < -eps:
                    continue
                l0 = 1.0 - l1 - l2 - l3
                if l0 < -eps:
                    continue
                out[n] = t
                if want_bary:
                    bary[n, 0] = l0
                    bary[n, 1] = l1
                    bary[n, 2] = l2
                    bary[n, 3] = l3
                break


class NumbaGrid:
    """The CPU grid: same method as the torch path, built and queried by the kernels above."""

    def __init__(self, V: np.ndarray, T: np.ndarray, cells_per_tet: float, eps: float, max_res: int):
        V = np.ascontiguousarray(V, dtype=np.float64)
        T = np.ascontiguousarray(T, dtype=np.int64)
        M = len(T)
        self.R = np.empty((M, 3, 4))
        tlo, thi = np.empty((M, 3)), np.empty((M, 3))
        self.n_degenerate = int(tet_rows(V, T, self.R, tlo, thi))
        self.eps = eps
        self.glo = V.min(0)
        extent = np.maximum(V.max(0) - self.glo, 1e-12)
        h = (extent.prod() / (cells_per_tet * M)) ** (1.0 / 3.0)
        self.res = np.clip(np.ceil(extent / h), 1, max_res).astype(np.int64)
        self.inv = self.res / extent
        self.n_cells = int(self.res.prod())
        counts = np.empty(M, np.int64)
        bbox_counts(tlo, thi, self.glo, self.inv, self.res, counts)
        offsets = np.zeros(M + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        # One chunk of tets per thread, balanced by bounding-box pairs; the result does not
        # depend on the number of chunks (within a cell, tets end up in index order, then by score).
        n_chunks = max(1, numba.get_num_threads())
        bounds = np.searchsorted(offsets, np.linspace(0, offsets[-1], n_chunks + 1)).astype(np.int64)
        bounds[0], bounds[-1] = 0, M
        pair_cell = np.empty(offsets[-1], np.int32)
        pair_key = np.empty(offsets[-1], np.float32)
        hist = np.zeros((n_chunks, self.n_cells), np.int64)
        fill_pairs(self.R, tlo, thi, self.glo, self.inv, self.res, eps, offsets, bounds, pair_cell, pair_key, hist)
        self.cell_start = np.empty(self.n_cells + 1, np.int64)
        cell_offsets(hist, self.cell_start)
        n_pairs = int(self.cell_start[-1])
        self.cell_tets = np.empty(n_pairs, np.int32)
        cell_key = np.empty(n_pairs, np.float32)
        scatter_pairs(pair_cell, pair_key, offsets, bounds, hist, self.cell_tets, cell_key)
        sort_cells(self.cell_start, self.cell_tets, cell_key)

    def query(self, P: np.ndarray, want_bary: bool):
        P = np.ascontiguousarray(P, dtype=np.float64)
        out = np.empty(len(P), np.int64)
        bary = np.zeros((len(P), 4)) if want_bary else np.zeros((1, 4))
        query(P, self.glo, self.inv, self.res, self.cell_start, self.cell_tets, self.R, self.eps, out, bary, want_bary)
        return out, (bary if want_bary else None)
