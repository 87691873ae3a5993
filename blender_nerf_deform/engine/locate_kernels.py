"""Fused CPU kernels (numba) for point location in a tet cage: grid build and query.

Why: on CPU the torch formulation of `point_location.py` spends its time in
materialised (pairs, 12) gathers and per-round compactions; on the project's
2-core machine it runs at about igl's speed, not above it (BENCHMARKS.md).
These kernels do the same uniform-grid method (cells list the tets that
overlap them, pruned by the tets' face planes) with the per-tet and per-point
work in registers: build in one parallel pass (bounding-box cells, pruned by the
face planes) and a counting sort by cell; query parallel over points, testing each point's candidates
until the first hit. Always float64.

Used only for CPU tensors; CUDA takes the torch path, so the renderer runs the
same method everywhere. numba is optional (as for the hash-grid kernels): without
it the torch path runs on CPU too, only slower.
"""

from __future__ import annotations

import numpy as np

try:  # numba is an optional accelerator, pinned in requirements.txt.
    from numba import njit, prange

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    HAVE_NUMBA = False


if HAVE_NUMBA:

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
            c23 = (e[1, 1] * e[2, 2] - e[1, 2] * e[2, 1], e[1, 2] * e[2, 0] - e[1, 0] * e[2, 2], e[1, 0] * e[2, 1] - e[1, 1] * e[2, 0])
            c31 = (e[2, 1] * e[0, 2] - e[2, 2] * e[0, 1], e[2, 2] * e[0, 0] - e[2, 0] * e[0, 2], e[2, 0] * e[0, 1] - e[2, 1] * e[0, 0])
            c12 = (e[0, 1] * e[1, 2] - e[0, 2] * e[1, 1], e[0, 2] * e[1, 0] - e[0, 0] * e[1, 2], e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0])
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
    def _box_may_overlap(R, t, cx, cy, cz, hx, hy, hz, eps):
        """False if the box (centre c, half sizes h) lies wholly outside one face plane of tet t."""
        s0 = 1.0
        r0x = 0.0
        r0y = 0.0
        r0z = 0.0
        for r in range(3):
            gx, gy, gz = R[t, r, 0], R[t, r, 1], R[t, r, 2]
            lam = gx * cx + gy * cy + gz * cz + R[t, r, 3]
            if lam + abs(gx) * hx + abs(gy) * hy + abs(gz) * hz < -eps:
                return False
            s0 -= lam
            r0x += gx
            r0y += gy
            r0z += gz
        return s0 + abs(r0x) * hx + abs(r0y) * hy + abs(r0z) * hz >= -eps

    @njit(inline="always")
    def _cell_range(tlo, thi, t, c, glo, inv, res):
        a = int(np.floor((tlo[t, c] - glo[c]) * inv[c]))
        b = int(np.floor((thi[t, c] - glo[c]) * inv[c]))
        return max(0, min(a, res[c] - 1)), max(0, min(b, res[c] - 1))

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
    def fill_pairs(R, tlo, thi, glo, inv, res, eps, offsets, pair_cell):
        M = R.shape[0]
        hx, hy, hz = 0.5 / inv[0], 0.5 / inv[1], 0.5 / inv[2]
        rx, ry = res[0], res[1]
        for t in prange(M):
            x0, x1 = _cell_range(tlo, thi, t, 0, glo, inv, res)
            y0, y1 = _cell_range(tlo, thi, t, 1, glo, inv, res)
            z0, z1 = _cell_range(tlo, thi, t, 2, glo, inv, res)
            n = offsets[t]
            single = x0 == x1 and y0 == y1 and z0 == z1
            for k in range(z0, z1 + 1):
                for j in range(y0, y1 + 1):
                    for i in range(x0, x1 + 1):
                        if single or _box_may_overlap(R, t, glo[0] + (i + 0.5) / inv[0], glo[1] + (j + 0.5) / inv[1], glo[2] + (k + 0.5) / inv[2], hx, hy, hz, eps):
                            pair_cell[n] = (k * ry + j) * rx + i
                        else:
                            pair_cell[n] = -1  # pruned: the cell lies outside one of the tet's face planes
                        n += 1

    @njit(cache=True)
    def bucket_by_cell(pair_cell, offsets, n_cells, cell_start, cell_tets, tet_order):
        """Counting sort of the (tet, cell) pairs by cell; within a cell tets come in `tet_order`.
        """
        counts = np.zeros(n_cells + 1, np.int64)
        for p in range(pair_cell.shape[0]):
            if pair_cell[p] >= 0:
                counts[pair_cell[p] + 1] += 1
        for c in range(n_cells):
            counts[c + 1] += counts[c]
        cell_start[:] = counts
        M = offsets.shape[0] - 1
        for q in range(M):
            t = tet_order[q]
            for p in range(offsets[t], offsets[t + 1]):
                c = pair_cell[p]
                if c < 0:
                    continue
                cell_tets[counts[c]] = t
                counts[c] += 1

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
        pair_cell = np.empty(offsets[-1], np.int64)
        fill_pairs(self.R, tlo, thi, self.glo, self.inv, self.res, eps, offsets, pair_cell)
        self.cell_start = np.empty(self.n_cells + 1, np.int64)
        self.cell_tets = np.empty(offsets[-1], np.int32)  # (over-allocated by the pruned pairs)
        # Tets keep their index order within a cell: cages from fTetWild number
        # neighbouring tets closely, so this order reads R with good locality
        # (ordering by size instead was measured slower: more cache misses).
        tet_order = np.arange(M)
        bucket_by_cell(pair_cell, offsets, self.n_cells, self.cell_start, self.cell_tets, tet_order)

    def query(self, P: np.ndarray, want_bary: bool):
        P = np.ascontiguousarray(P, dtype=np.float64)
        out = np.empty(len(P), np.int64)
        bary = np.zeros((len(P), 4)) if want_bary else np.zeros((1, 4))
        query(P, self.glo, self.inv, self.res, self.cell_start, self.cell_tets, self.R, self.eps, out, bary, want_bary)
        return out, (bary if want_bary else None)
