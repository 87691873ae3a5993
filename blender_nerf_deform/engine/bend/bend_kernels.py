"""Fused CPU kernels (numba) of the ray bender: the per-sample map, the per-pose tet affines and
the deformed occupancy.

`cage_bend.CageBend` runs these on CPU when `backend.use_kernels` says so and
the same computation in torch elsewhere (CUDA); the tests check both agree.
"""

from __future__ import annotations

import numpy as np

from .. import backend

# A density scale this close to 1 is 1: an identity pose's float32 affines (I up to rounding) leave
# every density exactly as in an undeformed render.
DENSITY_SCALE_SNAP = 1e-5

if backend.HAVE_NUMBA:
    from ..kernel_cache import njit, prange

    @njit(parallel=True, cache=True)
    def map_samples(
        P, D, tet, located, linear, offset, rotation, rotate, occ, olo, oext, ores, out_p, out_d, keep, density, scale
    ):
        """Per sample: the tet's affine (or identity outside every deformed tet), the rotated view
        direction, whether the rest point lies in an occupied cell of the NeRF's grid and (when
        `density`) the density scale |A d| / |d|: how long a unit step along the ray is in rest space
        (`density_scale`; 1 outside every tet, and within DENSITY_SCALE_SNAP of 1 it is exactly 1)."""
        for n in prange(P.shape[0]):
            x, y, z = P[n, 0], P[n, 1], P[n, 2]
            if tet[n] >= 0:
                t = located[tet[n]]
                px = linear[t, 0, 0] * x + linear[t, 0, 1] * y + linear[t, 0, 2] * z + offset[t, 0]
                py = linear[t, 1, 0] * x + linear[t, 1, 1] * y + linear[t, 1, 2] * z + offset[t, 1]
                pz = linear[t, 2, 0] * x + linear[t, 2, 1] * y + linear[t, 2, 2] * z + offset[t, 2]
                dx, dy, dz = D[n, 0], D[n, 1], D[n, 2]
                if density:
                    ax = linear[t, 0, 0] * dx + linear[t, 0, 1] * dy + linear[t, 0, 2] * dz
                    ay = linear[t, 1, 0] * dx + linear[t, 1, 1] * dy + linear[t, 1, 2] * dz
                    az = linear[t, 2, 0] * dx + linear[t, 2, 1] * dy + linear[t, 2, 2] * dz
                    dd = dx * dx + dy * dy + dz * dz
                    s = np.sqrt((ax * ax + ay * ay + az * az) / dd) if dd > 0 else 1.0
                    scale[n] = 1.0 if abs(s - 1.0) <= DENSITY_SCALE_SNAP else s
                if rotate:
                    out_d[n, 0] = rotation[t, 0, 0] * dx + rotation[t, 0, 1] * dy + rotation[t, 0, 2] * dz
                    out_d[n, 1] = rotation[t, 1, 0] * dx + rotation[t, 1, 1] * dy + rotation[t, 1, 2] * dz
                    out_d[n, 2] = rotation[t, 2, 0] * dx + rotation[t, 2, 1] * dy + rotation[t, 2, 2] * dz
                else:
                    out_d[n, 0], out_d[n, 1], out_d[n, 2] = dx, dy, dz
            else:
                px, py, pz = x, y, z
                out_d[n, 0], out_d[n, 1], out_d[n, 2] = D[n, 0], D[n, 1], D[n, 2]
                if density:
                    scale[n] = 1.0
            out_p[n, 0], out_p[n, 1], out_p[n, 2] = px, py, pz
            # Same float32 formula as OccupancyGrid.cell_index, so identity poses match undeformed renders.
            gx = np.floor((px - olo[0]) / oext[0] * ores)
            gy = np.floor((py - olo[1]) / oext[1] * ores)
            gz = np.floor((pz - olo[2]) / oext[2] * ores)
            r = int(ores)
            if gx >= 0 and gy >= 0 and gz >= 0 and gx < ores and gy < ores and gz < ores:
                keep[n] = occ[int(gx) + r * (int(gy) + r * int(gz))]
            else:
                keep[n] = False

    @njit(parallel=True, cache=True)
    def cell_images(ijk, corner_tet, rest_lo, rest_cell, forward, lo, hi):
        """Box of each occupied rest cell's image: the cell sent through the forward affine of every
        tet holding one of its corners (identity for corners outside the rest cage)."""
        for c in prange(ijk.shape[0]):
            for a in range(3):
                lo[c, a] = np.inf
                hi[c, a] = -np.inf
            for j in range(8):
                t = corner_tet[c, j]
                seen = False
                for q in range(j):
                    if corner_tet[c, q] == t:
                        seen = True
                if seen:
                    continue
                for k in range(8):
                    x = rest_lo[0] + (ijk[c, 0] + (k & 1)) * rest_cell[0]
                    y = rest_lo[1] + (ijk[c, 1] + ((k >> 1) & 1)) * rest_cell[1]
                    z = rest_lo[2] + (ijk[c, 2] + (k >> 2)) * rest_cell[2]
                    if t >= 0:
                        qx = forward[t, 0, 0] * x + forward[t, 0, 1] * y + forward[t, 0, 2] * z + forward[t, 0, 3]
                        qy = forward[t, 1, 0] * x + forward[t, 1, 1] * y + forward[t, 1, 2] * z + forward[t, 1, 3]
                        qz = forward[t, 2, 0] * x + forward[t, 2, 1] * y + forward[t, 2, 2] * z + forward[t, 2, 3]
                    else:
                        qx, qy, qz = x, y, z
                    lo[c, 0] = min(lo[c, 0], qx)
                    lo[c, 1] = min(lo[c, 1], qy)
                    lo[c, 2] = min(lo[c, 2], qz)
                    hi[c, 0] = max(hi[c, 0], qx)
                    hi[c, 1] = max(hi[c, 1], qy)
                    hi[c, 2] = max(hi[c, 2], qz)

    @njit(parallel=True, cache=True)
    def mark_boxes(i0, i1, r, mask):
        """Set every grid cell of every box [i0, i1] (inclusive); concurrent writes all store True."""
        for c in prange(i0.shape[0]):
            for z in range(i0[c, 2], i1[c, 2] + 1):
                for y in range(i0[c, 1], i1[c, 1] + 1):
                    for x in range(i0[c, 0], i1[c, 0] + 1):
                        mask[x + r * (y + r * z)] = True

    @njit(cache=True)
    def _inv3(a, out):
        """Closed-form inverse of a 3x3 matrix into `out`; returns its determinant (0: left unset)."""
        c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
        c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
        c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
        det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
        if det == 0.0:
            return det
        r = 1.0 / det
        out[0, 0], out[1, 0], out[2, 0] = c00 * r, c01 * r, c02 * r
        out[0, 1] = (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) * r
        out[0, 2] = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]) * r
        out[1, 1] = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) * r
        out[1, 2] = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) * r
        out[2, 1] = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) * r
        out[2, 2] = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) * r
        return det

    @njit(parallel=True, cache=True)
    def pose_tets(
        rest_edges,
        rest_edges_inv,
        rest_first,
        rest_det,
        deformed,
        tets,
        linear,
        offset,
        rotation,
        forward,
        det_f,
        needs_svd,
    ):
        """Per tet of one pose, in one pass: the deformed→rest affine (`linear`, `offset`), the
        rest→deformed one (`forward`, 3x4), det F (deformed / rest volume, signed) and the rotation
        of the polar decomposition of `linear` (scaled Newton iteration, Higham; converges for
        det > 0). Flat tets get NaN affines; inverted ones (det < 0) are flagged in `needs_svd`
        for the SVD-based closest rotation. What numpy's batched inv / svd did, in one pass."""
        for t in prange(tets.shape[0]):
            a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
            dd = np.empty((3, 3))
            for i in range(3):
                dd[i, 0] = deformed[b, i] - deformed[a, i]
                dd[i, 1] = deformed[c, i] - deformed[a, i]
                dd[i, 2] = deformed[d, i] - deformed[a, i]
            inv = np.empty((3, 3))
            det = _inv3(dd, inv)
            det_f[t] = det / rest_det[t]
            needs_svd[t] = False
            # forward F = dd @ rest_edges_inv, offset = d_a - F r_a
            for i in range(3):
                acc = deformed[a, i]
                for j in range(3):
                    f = (
                        dd[i, 0] * rest_edges_inv[t, 0, j]
                        + dd[i, 1] * rest_edges_inv[t, 1, j]
                        + dd[i, 2] * rest_edges_inv[t, 2, j]
                    )
                    forward[t, i, j] = f
                    acc -= f * rest_first[t, j]
                forward[t, i, 3] = acc
            if det == 0.0 or not np.isfinite(det):
                for i in range(3):
                    offset[t, i] = np.nan
                    for j in range(3):
                        linear[t, i, j] = np.nan
                        rotation[t, i, j] = 1.0 if i == j else 0.0
                continue
            m = np.empty((3, 3))
            for i in range(3):
                acc = rest_first[t, i]
                for j in range(3):
                    v = (
                        rest_edges[t, i, 0] * inv[0, j]
                        + rest_edges[t, i, 1] * inv[1, j]
                        + rest_edges[t, i, 2] * inv[2, j]
                    )
                    m[i, j] = v
                    linear[t, i, j] = v
                for j in range(3):
                    acc -= m[i, j] * deformed[a, j]
                offset[t, i] = acc
            if det * rest_det[t] < 0.0:
                needs_svd[t] = True
                continue
            x = m.copy()
            xi = np.empty((3, 3))
            for _ in range(40):
                dx = _inv3(x, xi)
                if dx == 0.0:
                    needs_svd[t] = True
                    break
                g = abs(dx) ** (-1.0 / 3.0)
                change = 0.0
                for i in range(3):
                    for j in range(3):
                        nxt = 0.5 * (g * x[i, j] + xi[j, i] / g)
                        change = max(change, abs(nxt - x[i, j]))
                        x[i, j] = nxt
                if change < 1e-13:
                    break
            for i in range(3):
                for j in range(3):
                    rotation[t, i, j] = x[i, j]
