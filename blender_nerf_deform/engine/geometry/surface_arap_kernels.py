"""The local step of surface_arap.SurfaceArap as one fused CPU kernel (numba): per tet its best
rotation, its share of the right-hand side, its ARAP energy and its det F, in one pass over the tets.

Why not arap_kernels.arap_local: that kernel finds each rotation by cyclic Jacobi sweeps on Horn's
4x4 matrix (about 0.8 us a tet, most of a surface ARAP iteration on the demo's cages), and the solve
then reads every tet's corners again for det F. Here the top eigenvalue of Horn's matrix comes from
Newton's method on its characteristic polynomial and the eigenvector from the adjugate (Theobald's
QCP, Acta Cryst. A 2005): a few dozen flops, the same rotation to round-off. Where the top eigenvalue
is (nearly) repeated the adjugate says nothing, and the tet falls back on the Jacobi sweeps.
"""

from __future__ import annotations

import numpy as np

from .. import backend
from .arap_kernels import EDGE_END, EDGE_START

if backend.HAVE_NUMBA:
    from ..kernel_cache import njit
    from .arap_kernels import horn_matrix, jacobi_top_eigenvector, quaternion_rotation

    @njit(inline="always")
    def _cofactor(M, r, c):
        """(-1)^(r+c) x the determinant of the 4x4 M without row r and column c."""
        r0, r1, r2 = (1, 2, 3) if r == 0 else ((0, 2, 3) if r == 1 else ((0, 1, 3) if r == 2 else (0, 1, 2)))
        c0, c1, c2 = (1, 2, 3) if c == 0 else ((0, 2, 3) if c == 1 else ((0, 1, 3) if c == 2 else (0, 1, 2)))
        d = (
            M[r0, c0] * (M[r1, c1] * M[r2, c2] - M[r1, c2] * M[r2, c1])
            - M[r0, c1] * (M[r1, c0] * M[r2, c2] - M[r1, c2] * M[r2, c0])
            + M[r0, c2] * (M[r1, c0] * M[r2, c1] - M[r1, c1] * M[r2, c0])
        )
        return -d if (r + c) % 2 else d

    @njit(inline="always")
    def _qcp_top_eigenvector(A, M, out):
        """Unit eigenvector of the largest eigenvalue of Horn's symmetric traceless 4x4 A, into out (M:
        scratch); False where that eigenvalue is too close to the next for the adjugate to give it."""
        sq = 0.0  # sum of the eigenvalues' squares
        for i in range(4):
            for j in range(4):
                sq += A[i, j] * A[i, j]
        if sq <= 0.0:
            return False
        scale = np.sqrt(sq)
        # det(x I - A) = x^4 + c2 x^2 + c1 x + c0 (A is traceless): c2 = -sq / 2, c1 = -(sum of the
        # principal 3x3 minors), c0 = det A.
        c1 = 0.0
        for i in range(4):
            c1 -= _cofactor(A, i, i)
        c0 = 0.0
        for j in range(4):
            c0 += A[0, j] * _cofactor(A, 0, j)
        c2 = -0.5 * sq
        # Newton from above the largest root (no eigenvalue exceeds sqrt(sq)): the polynomial is convex
        # and increasing there (every root is real), so the iterates fall monotonically, quadratically
        # where the root is simple.
        x = scale
        for _ in range(60):
            x2 = x * x
            dp = 4.0 * x2 * x + 2.0 * c2 * x + c1
            if dp <= 0.0:
                break
            step = ((x2 + c2) * x2 + c1 * x + c0) / dp
            x -= step
            if abs(step) <= 1e-12 * scale:
                break
        # adj(A - x I) = prod(gaps to the other eigenvalues) q q^T: its column with the largest diagonal
        # is the eigenvector. Below 1e-3 scale^3 a gap may be so small that x's round-off (~1e-16 scale^2
        # / gap) leaves the eigenvector off by more than ~1e-9: Jacobi's sweeps then.
        for i in range(4):
            for j in range(4):
                M[i, j] = A[i, j]
            M[i, i] -= x
        k, best = 0, 0.0
        for i in range(4):
            d = abs(_cofactor(M, i, i))
            if d > best:
                k, best = i, d
        if best < 1e-3 * sq * scale:
            return False
        n = 0.0
        for i in range(4):
            out[i] = _cofactor(M, i, k)
            n += out[i] * out[i]
        n = np.sqrt(n)
        for i in range(4):
            out[i] /= n
        return True

    @njit(cache=True)
    def surface_local(U, T, W, E, inv_det0, B, J):
        """Per tet: covariance of its weighted edges, the best rotation R (Horn's quaternion: det R = +1),
        its share of the global step's right-hand side added into B at its corners, and J = det F (the
        deformed edges' det x `inv_det0`). Returns the ARAP energy, sum w |u_i - u_j - R (v_i - v_j)|^2.

        One thread: a call is short on the demo's cages, where a parallel region's start costs as
        much and stalls whenever another process holds a core (as a render beside Blender does)."""
        A = np.empty((4, 4))
        M = np.empty((4, 4))
        q = np.empty(4)
        S = np.empty((3, 3))
        R = np.empty((3, 3))
        B[:] = 0.0
        total = 0.0
        for t in range(T.shape[0]):
            horn_matrix(U, T, W, E, t, S, A)
            if not _qcp_top_eigenvector(A, M, q):
                k = jacobi_top_eigenvector(A, M)  # overwrites A; the eigenvectors into M's columns
                for c in range(4):
                    q[c] = M[c, k]
            nq = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
            q0, q1, q2, q3 = q[0] / nq, q[1] / nq, q[2] / nq, q[3] / nq
            quaternion_rotation(q0, q1, q2, q3, R)
            for e in range(6):
                i = T[t, EDGE_START[e]]
                j = T[t, EDGE_END[e]]
                w = W[t, e]
                for a in range(3):
                    re = R[a, 0] * E[t, e, 0] + R[a, 1] * E[t, e, 1] + R[a, 2] * E[t, e, 2]
                    B[i, a] += w * re
                    B[j, a] -= w * re
                    d = U[i, a] - U[j, a] - re
                    total += w * d * d
            p0, p1, p2, p3 = T[t, 0], T[t, 1], T[t, 2], T[t, 3]
            ax, ay, az = U[p1, 0] - U[p0, 0], U[p1, 1] - U[p0, 1], U[p1, 2] - U[p0, 2]
            bx, by, bz = U[p2, 0] - U[p0, 0], U[p2, 1] - U[p0, 1], U[p2, 2] - U[p0, 2]
            cx, cy, cz = U[p3, 0] - U[p0, 0], U[p3, 1] - U[p0, 1], U[p3, 2] - U[p0, 2]
            J[t] = (ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)) * inv_det0[t]
        return total
