"""Fused CPU kernels (numba) of our ARAP solver: per-tet best rotations (local step) and the
right-hand side gathered per vertex (global step).

Why hand-written: libigl's `arap_solve` recomputes its local step in Eigen
without threads and costs about twice our per-frame time;
`deform.ArapDeformer` keeps libigl as its reference and its fallback without numba.
"""

from __future__ import annotations

import numpy as np

from .. import backend

# Edges of a tet in the column order of igl.cotmatrix_entries.
TET_EDGES = np.array([[1, 2], [2, 0], [0, 1], [3, 0], [3, 1], [3, 2]], dtype=np.int64)
EDGE_START = TET_EDGES[:, 0].copy()  # module constants, frozen into the kernels
EDGE_END = TET_EDGES[:, 1].copy()

if backend.HAVE_NUMBA:  # without numba ARAP runs libigl's solver
    from ..kernel_cache import njit, prange


if backend.HAVE_NUMBA:

    @njit(inline="always")
    def horn_matrix(U, T, W, E, t, S, A):
        """Tet t's covariance S = sum over its edges of w (v_i - v_j)(u_i - u_j)^T (rest edges E, weights
        W, deformed vertices U) and Horn's symmetric 4x4 A of S: its top eigenvector is the quaternion
        of the rotation that best maps the rest edges onto the deformed ones."""
        for a in range(3):
            for b in range(3):
                S[a, b] = 0.0
        for e in range(6):
            i = T[t, EDGE_START[e]]
            j = T[t, EDGE_END[e]]
            w = W[t, e]
            for a in range(3):  # S = sum w (v_i - v_j)(u_i - u_j)^T: source x target
                va = w * E[t, e, a]
                for b in range(3):
                    S[a, b] += va * (U[i, b] - U[j, b])
        sxx, sxy, sxz = S[0, 0], S[0, 1], S[0, 2]
        syx, syy, syz = S[1, 0], S[1, 1], S[1, 2]
        szx, szy, szz = S[2, 0], S[2, 1], S[2, 2]
        A[0, 0] = sxx + syy + szz
        A[0, 1] = A[1, 0] = syz - szy
        A[0, 2] = A[2, 0] = szx - sxz
        A[0, 3] = A[3, 0] = sxy - syx
        A[1, 1] = sxx - syy - szz
        A[1, 2] = A[2, 1] = sxy + syx
        A[1, 3] = A[3, 1] = szx + sxz
        A[2, 2] = -sxx + syy - szz
        A[2, 3] = A[3, 2] = syz + szy
        A[3, 3] = -sxx - syy + szz

    @njit(inline="always")
    def quaternion_rotation(q0, q1, q2, q3, R):
        """R = the rotation of the unit quaternion (q0, q1, q2, q3)."""
        R[0, 0] = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
        R[0, 1] = 2.0 * (q1 * q2 - q0 * q3)
        R[0, 2] = 2.0 * (q1 * q3 + q0 * q2)
        R[1, 0] = 2.0 * (q1 * q2 + q0 * q3)
        R[1, 1] = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3
        R[1, 2] = 2.0 * (q2 * q3 - q0 * q1)
        R[2, 0] = 2.0 * (q1 * q3 - q0 * q2)
        R[2, 1] = 2.0 * (q2 * q3 + q0 * q1)
        R[2, 2] = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3

    @njit(inline="always")
    def jacobi_top_eigenvector(A, Q):
        """Eigenvector of the largest eigenvalue of the symmetric 4x4 A (overwritten), into Q[:, k]; returns k.

        Cyclic Jacobi rotations: robust for repeated eigenvalues, and a 4x4
        needs a few sweeps. Hand-written because numba's np.linalg.eigh is a
        LAPACK call per matrix, too slow for 100k+ tiny matrices.
        """
        for i in range(4):
            for j in range(4):
                Q[i, j] = 1.0 if i == j else 0.0
        scale = 0.0
        for i in range(4):
            for j in range(4):
                scale += A[i, j] * A[i, j]
        for _sweep in range(12):
            off = 0.0
            for p in range(3):
                for q in range(p + 1, 4):
                    off += A[p, q] * A[p, q]
            if off <= 1e-30 * scale or off == 0.0:
                break
            for p in range(3):
                for q in range(p + 1, 4):
                    apq = A[p, q]
                    if apq == 0.0:
                        continue
                    theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                    t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                    c = 1.0 / np.sqrt(t * t + 1.0)
                    s = t * c
                    for k in range(4):  # A <- A J (columns p, q)
                        akp, akq = A[k, p], A[k, q]
                        A[k, p] = c * akp - s * akq
                        A[k, q] = s * akp + c * akq
                    for k in range(4):  # A <- J^T A (rows p, q)
                        apk, aqk = A[p, k], A[q, k]
                        A[p, k] = c * apk - s * aqk
                        A[q, k] = s * apk + c * aqk
                    for k in range(4):  # Q <- Q J
                        qkp, qkq = Q[k, p], Q[k, q]
                        Q[k, p] = c * qkp - s * qkq
                        Q[k, q] = s * qkp + c * qkq
        best = 0
        for i in range(1, 4):
            if A[i, i] > A[best, best]:
                best = i
        return best

    @njit(parallel=True, cache=True)
    def arap_local(U, T, W, E, corner_rhs, energy):
        """Per tet: covariance of its weighted edges, the best rotation R (Horn's quaternion
        form of the 3x3 orthogonal Procrustes problem, so det R = +1 always), then the
        tet's share of the global step's right-hand side at each corner, and its energy
        sum w |u_i - u_j - R (v_i - v_j)|^2.
        """
        m = T.shape[0]
        n_chunks = min(m, 256)
        for chunk in prange(n_chunks):
            A = np.empty((4, 4))
            Q = np.empty((4, 4))
            S = np.empty((3, 3))
            R = np.empty((3, 3))
            for t in range(chunk * m // n_chunks, (chunk + 1) * m // n_chunks):
                horn_matrix(U, T, W, E, t, S, A)
                k = jacobi_top_eigenvector(A, Q)
                q0, q1, q2, q3 = Q[0, k], Q[1, k], Q[2, k], Q[3, k]
                nq = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
                q0, q1, q2, q3 = q0 / np.sqrt(nq), q1 / np.sqrt(nq), q2 / np.sqrt(nq), q3 / np.sqrt(nq)
                quaternion_rotation(q0, q1, q2, q3, R)
                for c in range(4):
                    for a in range(3):
                        corner_rhs[t, c, a] = 0.0
                en = 0.0
                for e in range(6):
                    ci, cj = EDGE_START[e], EDGE_END[e]
                    i = T[t, ci]
                    j = T[t, cj]
                    w = W[t, e]
                    for a in range(3):
                        re = R[a, 0] * E[t, e, 0] + R[a, 1] * E[t, e, 1] + R[a, 2] * E[t, e, 2]
                        corner_rhs[t, ci, a] += w * re
                        corner_rhs[t, cj, a] -= w * re
                        d = U[i, a] - U[j, a] - re
                        en += w * d * d
                energy[t] = en

    @njit(parallel=True, cache=True)
    def gather_rhs(corner_rhs, start, slots, B):
        """B[v] = sum of the corner contributions of the tets around v (CSR `start`/`slots` into (t*4+corner))."""
        flat = corner_rhs.reshape(-1, 3)
        for v in prange(B.shape[0]):
            x = 0.0
            y = 0.0
            z = 0.0
            for s in range(start[v], start[v + 1]):
                x += flat[slots[s], 0]
                y += flat[slots[s], 1]
                z += flat[slots[s], 2]
            B[v, 0] = x
            B[v, 1] = y
            B[v, 2] = z
