"""A flip-free step after ARAP: the ARAP energy plus a barrier on det F, minimised without inverting a tet.

ARAP (elements energy, `deform.ArapDeformer`) knows nothing of orientation: with a pinned base and a
strongly turned handle on a coarse cage, a few tets near the bend come out inside out (det F < 0), a
fold in the picture. This step, run only where ARAP's result has a tet with det F below `threshold`
j (0.1), minimises

    E(U) = E_ARAP(U) + kappa * sum_t vol_t * b(J_t) + mu * sum_{i in handles, pins} |u_i - target_i|^2
    J_t = det F_t = vol_t(U) / vol_t(rest)
    b(J) = -(J - j)^2 log(J / j) for 0 < J < j,  0 for J >= j,  +inf for J <= 0

(the clamped log barrier of IPC, Li et al. 2020, on det F, as the "locally injective" line of work
bounds det F: SLIM, Rabinovich et al. 2017) from a flip-free start, with a line search that rejects
any step leaving a tet with J <= 0, so every iterate and the result are flip-free. b is C2 and
exactly 0 above j: a pose whose ARAP result has every J >= j is returned untouched, and as a pose
approaches trouble the barrier switches on smoothly (the result is continuous in the pose).

Why libigl's SLIM (`igl.slim_precompute` / `slim_solve`, which the binding has, tets included) is
not used: its energies are symmetric Dirichlet / ARAP / conformal without a threshold, so a frame
it repairs would no longer be ARAP's (a jump where the step switches on); it re-precomputes per
pose (the start is part of its precomputation), and its constraints are soft anyway.

The handles and pins are soft constraints (the mu term; mu = 1e4 x the largest diagonal entry of
L). Hard ones cannot work on a coarse cage: a tet can have all four corners on handles (the demo's
cage has tets spanning the middle and tip handles' regions), so the targets alone fix its det F,
negative in the demo's bent frames; only moving a handle vertex a little un-inverts it. The
residual is measured and reported (`handle_residual`): ~1e-5 of the cage's diagonal where nothing
forces a flip, up to ~1e-3 where the targets do.

The start, from the pose alone (not from the previous frame: a frame's result must not depend on
render order):
- ARAP's result itself, when it has no tet at J <= 0 (only some below j): already flip-free.
- otherwise ARAP's result "projected back": rest + s (U_arap - rest) with the largest s in [0, 1]
  (a fixed grid, then bisection) at which every tet keeps J >= j / 2: flip-free, its handles short
  of their targets until the penalty pulls them in.

Each iteration is a quasi-Newton step: the Hessian is ARAP's global-step matrix 2 L (the cotangent
Laplacian of the elements energy: with no barrier active and no penalty the step from the gradient
2 (L U - B(U)) is one local/global iteration), the penalty's 2 mu on the constrained vertices, and
the Gauss-Newton term kappa vol_t b''(J_t) g_t g_t^T of each tet below j (g_t = dJ_t/dU). L + mu P
is factored once per set of handles (SuperLU, on first need); up to WOODBURY_TETS barrier terms
enter by the Woodbury identity (no factorization per iteration), more by one sparse LU of the whole
matrix. Backtracking (Armijo) line search on E. Bounded by an iteration count (no clock: a result
must not depend on the machine's speed).

Targets that force a large flip (a handle region whose own affine is a reflection, handles pulled
through a pinned region) leave a residual above `max_residual` (5e-3 of the diagonal): then the
handles are put on their targets regardless (the correction spread over the free vertices by the
Laplacian), and of that and ARAP's own result the one with fewer inverted tets is returned, its
count reported.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..errors import EngineError
from . import arap_kernels

WOODBURY_TETS = 48  # up to this many tets below the threshold, their Hessian terms enter by Woodbury; more: one sparse LU


@dataclass
class InjectiveResult:
    vertices: np.ndarray
    ran: bool  # False: ARAP's result had no tet below the threshold and is returned as it was
    inverted_before: int  # tets with det F < 0 in ARAP's result
    inverted: int  # tets with det F < 0 in the result
    min_det_before: float
    min_det: float
    iterations: int  # quasi-Newton iterations of both phases
    handle_residual: float  # largest distance of a constrained vertex from its target before the final snap, / cage diagonal
    start: str  # "unchanged", "arap" (ARAP's result, flip-free), "projected" (s * ARAP's displacement), "rest"
    seconds: float


def tet_dets(U: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(M,) det[b-a, c-a, d-a] of each tet (6 x signed volume)."""
    P = U[T]
    e1, e2, e3 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]
    return np.einsum("mi,mi->m", e1, np.cross(e2, e3))


def barrier(J: np.ndarray, j: float) -> np.ndarray:
    """b(J) elementwise: 0 for J >= j, +inf for J <= 0."""
    out = np.zeros_like(J)
    low = J < j
    Jl = J[low]
    with np.errstate(divide="ignore", invalid="ignore"):
        out[low] = np.where(Jl > 0, -((Jl - j) ** 2) * np.log(np.maximum(Jl, 1e-300) / j), np.inf)
    return out


def _barrier_d1_d2(J: np.ndarray, j: float) -> tuple[np.ndarray, np.ndarray]:
    """b'(J), b''(J) for 0 < J < j."""
    x, r = J - j, np.log(J / j)
    return -2.0 * x * r - x * x / J, -2.0 * r - 4.0 * x / J + x * x / (J * J)


class InjectiveStep:
    """The flip-free step for one ArapDeformer (numba backend: its kernels, weights and factorization)."""

    def __init__(self, arap, threshold: float = 0.1, stiffness: float = 1000.0, penalty: float = 1e4,
                 max_residual: float = 5e-3):
        if arap.backend != "numba":
            raise EngineError("the flip-free step needs the numba ARAP backend (its kernels and factorization)")
        if not 0.0 < threshold < 1.0:
            raise EngineError(f"the flip-free step's det F threshold must lie in (0, 1), got {threshold}")
        self.arap = arap
        self.j = float(threshold)
        self.tets = arap.tets
        self.rest = arap.rest
        self.det0 = tet_dets(self.rest, self.tets)
        if (self.det0 <= 0).any():
            raise EngineError(f"the rest cage has {int((self.det0 <= 0).sum())} tets that are not positively oriented")
        self.vol0 = self.det0 / 6.0
        # kappa = stiffness / j. Against the penalty (a tet with four constrained corners) the barrier
        # settles where kappa vol b'(J) meets mu x residual: stiffness 1000 keeps such a tet at J ~ 0.01
        # with a residual ~ 1e-3 of the diagonal on the demo (stiffness 10: J ~ 2e-4, residual 4e-4).
        self.kappa = float(stiffness) / self.j
        self.b = arap.b
        n = len(self.rest)
        self.constrained = np.zeros(n, dtype=bool)
        self.constrained[self.b] = True
        self.free = arap._free
        self.L = arap._L
        self.mu = float(penalty) * float(self.L.diagonal().max())
        self.max_residual = float(max_residual)
        self._soft_lu = None
        self._corner = np.empty((len(self.tets), 4, 3))
        self._tet_energy = np.empty(len(self.tets))
        self._B = np.empty((n, 3))

    # -- energy -------------------------------------------------------------------------------
    def _evaluate(self, U: np.ndarray, bc: np.ndarray):
        """(E, J, B): the energy (inf if a tet has J <= 0), det F per tet, the ARAP right-hand side at U."""
        J = tet_dets(U, self.tets) / self.det0
        if not (J > 0).all():
            return np.inf, J, None
        U = np.ascontiguousarray(U)
        arap_kernels.arap_local(U, self.tets, self.arap._W, self.arap._E, self._corner, self._tet_energy)
        B = np.empty_like(self._B)
        arap_kernels.gather_rhs(self._corner, self.arap._start, self.arap._slots, B)
        E = float(self._tet_energy.sum()) + self.kappa * float((self.vol0 * barrier(J, self.j)).sum())
        E += self.mu * float(((U[self.b] - bc) ** 2).sum())
        return E, J, B

    def _barrier_terms(self, U: np.ndarray, J: np.ndarray):
        """Active tets (J < j), dJ/dU per corner (k, 4, 3), kappa vol b'(J) and kappa vol b''(J)."""
        act = np.flatnonzero(J < self.j)
        P = U[self.tets[act]]
        e1, e2, e3 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]
        g = np.empty((len(act), 4, 3))
        g[:, 1], g[:, 2], g[:, 3] = np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)
        g[:, 1:] /= self.det0[act, None, None]
        g[:, 0] = -g[:, 1:].sum(1)
        d1, d2 = _barrier_d1_d2(J[act], self.j)
        w = self.kappa * self.vol0[act]
        return act, g, w * d1, w * d2

    # -- one minimisation phase -----------------------------------------------------------------
    def _minimise(self, U: np.ndarray, bc: np.ndarray, max_iter: int, tol: float):
        """Quasi-Newton with a flip-rejecting Armijo line search from the flip-free U; every vertex moves,
        the constrained ones held by the penalty."""
        solve_A = self._soft_solver()
        rows = np.arange(len(U))
        A_matrix = self._soft_matrix
        where = np.full(len(U), -1, dtype=np.int64)
        where[rows] = np.arange(len(rows))
        E, J, B = self._evaluate(U, bc)
        if not np.isfinite(E):
            raise EngineError("internal: the flip-free step started from a configuration with an inverted tet")
        diag = self.arap.diag
        it = 0
        for it in range(1, max_iter + 1):
            G = 2.0 * (self.L @ U - B)
            G[self.b] += 2.0 * self.mu * (U[self.b] - bc)
            act, g, d1, d2 = self._barrier_terms(U, J)
            if len(act):
                np.add.at(G, self.tets[act].ravel(), (d1[:, None, None] * g).reshape(-1, 3))
            r = -G[rows]
            d = self._direction(solve_A, A_matrix, r, act, g, d2, where)
            slope = float((G[rows] * d).sum())
            if slope >= 0:  # no descent left (round-off)
                break
            alpha, accepted = 1.0, False
            while alpha > 1e-12:
                trial = U.copy()
                trial[rows] += alpha * d
                E_t, J_t, B_t = self._evaluate(trial, bc)
                if E_t <= E + 1e-4 * alpha * slope:
                    accepted = True
                    break
                alpha *= 0.5
            if not accepted:
                break
            moved = alpha * float(np.abs(d).max()) / diag
            U, E, J, B = trial, E_t, J_t, B_t
            if moved < tol:
                break
        return U, it

    def _direction(self, solve_A, A_matrix, r, act, g, d2, where):
        """(A + sum_t d2_t g_t g_t^T)^-1 r on the moving rows: with A's factorization and the Woodbury
        identity for a few barrier terms, else one sparse factorization of the whole matrix."""
        if len(act) <= WOODBURY_TETS:
            return self._woodbury(solve_A, r, act, g, d2, where)
        import scipy.sparse as sp
        from scipy.sparse.linalg import splu

        m = len(r)
        rows = where[self.tets[act]]  # (k, 4)
        dof = (rows[:, :, None] + m * np.arange(3)[None, None, :]).reshape(len(act), 12)  # coordinate-major
        keep = (rows >= 0).repeat(3, axis=1).reshape(len(act), 12)
        gg = g.reshape(len(act), 12) * keep
        vals = d2[:, None, None] * gg[:, :, None] * gg[:, None, :]
        ii = np.broadcast_to(dof[:, :, None], vals.shape)
        jj = np.broadcast_to(dof[:, None, :], vals.shape)
        ok = (ii >= 0) & (jj >= 0) & keep[:, :, None] & keep[:, None, :]
        Hb = sp.coo_matrix((vals[ok], (ii[ok], jj[ok])), shape=(3 * m, 3 * m))
        H = (sp.kron(sp.identity(3), 2.0 * A_matrix) + Hb).tocsc()
        lu = splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1, options=dict(SymmetricMode=True))
        return lu.solve(r.T.ravel()).reshape(3, m).T

    def _woodbury(self, solve_A, r, act, g, d2, where):
        """(A + sum_t d2_t g_t g_t^T)^-1 r with A^-1 from `solve_A` (the same A for x, y and z).

        Z = [sqrt(d2_t) g_t] touches only the active tets' vertices: A^-1 Z = W S with W the columns
        of A^-1 at those vertices (kept for the rest of this solve: A does not change, the active
        set changes slowly; not kept across solves, so a result does not depend on earlier ones)."""
        x = solve_A(r)
        if not len(act):
            return x
        k = len(act)
        verts, local = np.unique(self.tets[act], return_inverse=True)
        local = local.reshape(k, 4)
        missing = [v for v in verts.tolist() if v not in self._columns]
        if missing:
            unit = np.zeros((len(r), len(missing)))
            unit[missing, np.arange(len(missing))] = 1.0
            for v, col in zip(missing, solve_A(unit).T):
                self._columns[v] = col
        W = np.stack([self._columns[v] for v in verts.tolist()], axis=1)  # (n, nv)
        s = np.sqrt(np.maximum(d2, 0.0))
        S = np.zeros((3, len(verts), k))
        cols = np.arange(k)
        for c in range(4):
            for a in range(3):
                np.add.at(S[a], (local[:, c], cols), s * g[:, c, a])
        Wv = W[verts]
        C = np.eye(k) + sum(S[a].T @ Wv @ S[a] for a in range(3))
        y = np.linalg.solve(C, sum(S[a].T @ x[verts, a] for a in range(3)))
        return x - W @ np.stack([S[a] @ y for a in range(3)], axis=1)

    def _soft_solver(self):
        if self._soft_lu is None:
            import scipy.sparse as sp
            from scipy.sparse.linalg import splu

            P = sp.diags(self.constrained.astype(np.float64) * self.mu)
            A = (self.L + P).tocsc()
            self._soft_matrix = A
            self._soft_lu = splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1, options=dict(SymmetricMode=True))
        lu = self._soft_lu
        return lambda R: 0.5 * lu.solve(R)

    # -- the step -----------------------------------------------------------------------------
    def _projected_start(self, U_arap: np.ndarray) -> tuple[np.ndarray, float]:
        """rest + s (U_arap - rest) for the largest s found with every tet at J >= j / 2."""
        D = U_arap - self.rest

        def ok(s):
            return bool((tet_dets(self.rest + s * D, self.tets) >= 0.5 * self.j * self.det0).all())

        grid = np.linspace(0.0, 1.0, 17)
        lo = 0.0
        for s in grid[1:]:
            if not ok(s):
                hi = s
                break
            lo = s
        else:
            return self.rest + D, 1.0
        for _ in range(8):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if ok(mid) else (lo, mid)
        return self.rest + lo * D, lo

    def _snap(self, U: np.ndarray, bc: np.ndarray) -> np.ndarray:
        """The constrained vertices exactly on bc; their correction spread over the free vertices by
        the ARAP Laplacian (L_ff dU_f = -L_fb dU_b)."""
        out = U.copy()
        delta = bc - U[self.b]
        out[self.b] = bc
        if self.arap._lu is not None and len(self.free):
            out[self.free] += self.arap._lu.solve(-(self.arap._Lfb @ delta))
        return out

    def __call__(self, U_arap: np.ndarray, bc: np.ndarray, max_iter: int = 200, tol: float = 1e-6) -> InjectiveResult:
        t0 = time.perf_counter()
        U_arap = np.ascontiguousarray(U_arap, dtype=np.float64)
        J0 = tet_dets(U_arap, self.tets) / self.det0
        inv0, min0 = int((J0 < 0).sum()), float(J0.min())

        def result(V, start, iterations, residual):
            J = tet_dets(V, self.tets) / self.det0
            return InjectiveResult(V, start != "unchanged", inv0, int((J < 0).sum()), min0, float(J.min()), iterations,
                                   residual, start, time.perf_counter() - t0)

        if min0 >= self.j:
            return result(U_arap, "unchanged", 0, 0.0)
        self._columns = {}  # columns of A^-1 for this solve (_woodbury)
        if min0 > 0:
            U, start = U_arap, "arap"
        else:
            U, s = self._projected_start(U_arap)
            start = "projected" if s > 0 else "rest"
        U, iterations = self._minimise(U, bc, max_iter=max_iter, tol=tol)
        residual = float(np.linalg.norm(U[self.b] - bc, axis=1).max()) / self.arap.diag
        if residual <= self.max_residual:
            return result(U, start, iterations, residual)
        # The handles cannot reach their targets without a flip (contradictory targets): put them on
        # their targets anyway; of that and ARAP's own result, the one with fewer inverted tets.
        snapped = self._snap(U, bc)
        if int((tet_dets(snapped, self.tets) < 0).sum()) < inv0:
            return result(snapped, start + ", snapped", iterations, 0.0)
        return result(U_arap, start + ", gave up", iterations, 0.0)
