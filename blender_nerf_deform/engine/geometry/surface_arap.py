"""ARAP whose handles pull the extracted surface, minimised without ever inverting a tet.

The cage pose of a frame is the minimiser, over the cage's vertex positions U, of

    E(U) = E_ARAP(U) + sum_k w_k |c_k . U - t_k|^2 + kappa sum_t vol_t b(J_t)

- E_ARAP: the elements energy on the cage's tets (deform.ArapDeformer's, the same kernels).
- The constraints are points of the surface, not cage vertices: c_k is the barycentric row of a
  surface vertex of a handle's region (its tet's four corners, the embedding's weights), t_k that
  vertex's rest position moved by the handle's affine; a pinned surface vertex keeps its rest
  position. So does a cage vertex pinned where an edit region cut the scene (a unit row), and every
  vertex of a piece of the cage nothing else holds. The constraints are soft (least squares), as
  NeRF-Editing drives its cage through control points: where a coarse cage has a tet whose
  corners carry two handles' regions, no cage vertex is pinned to a target it cannot reach
  without folding; the surface follows its handle as closely as the rest of the cage allows
  (`surface_residual` says how closely).
- b(J) = -(J - j)^2 log(J / j) below j (0.1), 0 above, +inf at J <= 0, on J_t = det F_t: the clamped
  log barrier of IPC (Li et al. 2020) on det F, as the locally injective maps of SLIM (Rabinovich et
  al. 2017) bound it. C2 and exactly 0 above j: a pose that keeps every tet above j is pure ARAP.

Flip-free by construction: the solve starts from a flip-free configuration made from the pose alone
(the linear blend of the handles' affines; where that squeezes a tet below j, a few plain ARAP steps
from it; if they leave a tet below j / 2, pulled back towards the rest cage until every tet keeps
J >= j / 2; the rest cage itself at worst), and every step goes through a line search that refuses
any configuration with a tet at J <= 0. Each iterate, so the result, has no inverted tet, and a
frame's result depends on that frame's handles alone (never on the frame rendered before).

Each iteration is a quasi-Newton step whose matrix is 2 (L + C^T W C) (L the cotangent Laplacian of
the elements energy), factored once per set of handles: with no barrier active its full step is one
ARAP local/global iteration, and L-BFGS (Liu et al. 2017, the Laplacian as the initial Hessian)
corrects it with the last few steps' curvature: on the demo's bends 5-8 iterations where plain
local/global steps need 7-11. Tets below j add their Gauss-Newton terms kappa vol b''(J) g g^T by the
Woodbury identity (a few) or one sparse LU of the whole matrix (many); while the barrier acts the
steps are plain (its curvature changes too fast for secant pairs). Backtracking (Armijo) line
search on E. Bounded by an iteration count, not a clock (a result must not depend on the machine).

A handle whose affine is a reflection (a negative scale) asks for what no fold-free deformation
can give: the solve stays flip-free and its surface does not follow; `reflected` names it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import EngineError
from . import surface_arap_kernels
from .barycentric import signed_volumes
from .deform import ElementsEnergy, PieceBlend, affine_matrix, check_disjoint, tet_components

HISTORY = 5  # L-BFGS pairs kept
GUESS_STEPS = 3  # plain ARAP steps the first guess may take to undo the blend's folds
WOODBURY_TETS = 48  # up to this many tets below the threshold, their Hessian terms enter by Woodbury


@dataclass
class SurfacePose:
    vertices: np.ndarray  # (n, 3) the posed cage
    iterations: int
    converged: bool  # the last step moved less than `tol` x the cage's diagonal
    seconds: float
    min_det: float  # smallest det F over the tets (> 0: nothing inverted)
    surface_residual: float  # largest distance of a handle's surface vertex from its target, / that region's size
    barrier_tets: int  # tets below the barrier's threshold in the result (where the barrier shaped the pose)
    reflected: list = field(default_factory=list)  # names of handles whose affine is a reflection


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


class SurfaceArap:
    """The flip-free ARAP pose of a cage from handles on its embedded surface.

    Built once per cage, embedding and set of regions (the factorization); `solve(transforms)` per
    frame. `handle_points`: surface vertex indices of each handle's region; `pin_points`: surface
    vertices pinned at rest; `cage_pins`: cage vertices pinned at rest (the edit region's cut).
    `stiffness`: the constraints' weight against ARAP's, per cage vertex a region touches."""

    def __init__(
        self,
        rest_vertices: np.ndarray,
        tets: np.ndarray,
        embedding,
        handle_points: list,
        pin_points: np.ndarray | None = None,
        cage_pins: np.ndarray | None = None,
        names: list[str] | None = None,
        stiffness: float = 100.0,
        threshold: float = 0.1,
        barrier_stiffness: float = 1000.0,
    ):
        import scipy.sparse as sp
        from scipy.sparse.linalg import splu

        t0 = time.perf_counter()
        V = np.ascontiguousarray(rest_vertices, dtype=np.float64)
        T = np.ascontiguousarray(tets, dtype=np.int64)
        n = len(V)
        if not 0.0 < threshold < 1.0:
            raise EngineError(f"the det F threshold must lie in (0, 1), got {threshold}")
        self.rest, self.tets, self.j = V, T, float(threshold)
        self.diag = float(np.linalg.norm(np.ptp(V, axis=0)))
        self.vol0 = signed_volumes(V, T)
        if (self.vol0 <= 0).any():
            raise EngineError(f"the rest cage has {int((self.vol0 <= 0).sum())} tets that are not positively oriented")
        self.kappa = float(barrier_stiffness) / self.j

        self._elements = ElementsEnergy(V, T)
        self.L = self._elements.L
        self._inv_det0 = 1.0 / (6.0 * self.vol0)
        self._L_rest = self.L @ V

        # The constraint rows: the handles' surface vertices, the pinned ones, the cut's cage vertices.
        self.names = list(names or [f"handle {k}" for k in range(len(handle_points))])
        pins = [np.asarray(pin_points, dtype=np.int64)] if pin_points is not None and len(pin_points) else []
        regions = check_disjoint(
            list(handle_points) + pins, len(embedding.weights), self.names + ["the pinned region"] * len(pins)
        )
        unit = float(self.L.diagonal().mean()) * float(stiffness)
        rows_c, rows_w, row_weight, self._handle_rows, self._region_size = [], [], [], [], []
        rest_points = []
        for r in regions:
            corners, weights = embedding.corners[r], embedding.weights[r]
            touched = len(np.unique(corners[weights > 1e-12]))
            first = sum(len(c) for c in rows_c)
            rows_c.append(corners)
            rows_w.append(weights)
            # A region's pull is `stiffness` x ARAP's per cage vertex it touches, however many surface
            # vertices carry it (a dense mesh must not outweigh the cage's own stiffness).
            row_weight.append(np.full(len(r), unit * touched / len(r)))
            points = np.einsum("nk,nkc->nc", weights, V[corners])
            rest_points.append(points)
            self._handle_rows.append(np.arange(first, first + len(r)))
            self._region_size.append(max(float(np.linalg.norm(np.ptp(points, axis=0))), 1e-12 * self.diag))
        self._handle_rows = self._handle_rows[: len(handle_points)]
        held = np.zeros(n, dtype=bool)
        for c, w_ in zip(rows_c, rows_w):
            held[c[w_ > 1e-12]] = True
        fixed = np.zeros(0, dtype=np.int64)
        if cage_pins is not None and len(cage_pins):
            fixed = np.asarray(cage_pins, dtype=np.int64)
            if fixed.min() < 0 or fixed.max() >= n:
                raise EngineError(f"the cut's pinned cage vertices must index 0..{n - 1}")
        pieces = tet_components(n, T)
        loose = np.flatnonzero(~np.isin(pieces, pieces[np.union1d(np.flatnonzero(held), fixed)]))
        fixed = np.union1d(fixed, loose)  # a piece of the cage nothing holds stays where it is
        if not len(regions) and not len(fixed):
            raise EngineError("ARAP needs at least one handle or pinned region")
        if len(fixed):
            rows_c.append(np.repeat(fixed[:, None], 4, axis=1))
            rows_w.append(np.tile([1.0, 0.0, 0.0, 0.0], (len(fixed), 1)))
            row_weight.append(np.full(len(fixed), unit))
            rest_points.append(V[fixed])
        rows_c, rows_w, row_weight = np.concatenate(rows_c), np.concatenate(rows_w), np.concatenate(row_weight)
        self._rest_points = np.concatenate(rest_points)
        k = len(rows_c)
        self.C = sp.csr_matrix((rows_w.ravel(), (np.repeat(np.arange(k), 4), rows_c.ravel())), shape=(k, n))
        weighted = sp.diags(row_weight) @ self.C
        self.Q = (self.C.T @ weighted).tocsr()  # the constraints' quadratic form on the cage: C^T W C
        self.A = (self.L + self.Q).tocsc()
        self._handle_C = [self.C[rows] for rows in self._handle_rows]  # for the residual
        # The pulls in displacement form (D = U - rest; a row's target displacement is t_k - c_k.rest,
        # 0 for every pin), reduced to the cage's vertices once, so a frame costs O(cage), not O(rows):
        # for a handle with affine x -> x R^T + a, sum_k w_k |c_k D - (p_k M + a)|^2 with M = R^T - I
        # = D.QD - 2 D.(G_h M + g_h a^T) + tr(M^T S_h M) + 2 s_h.(M a) + w_h |a|^2.
        self._pull = []
        for rows in self._handle_rows:
            P, W_h = self._rest_points[rows], weighted[rows]
            self._pull.append(
                (
                    np.asarray(W_h.T @ P),
                    np.asarray(W_h.sum(0)).ravel(),
                    P.T @ (row_weight[rows, None] * P),
                    P.T @ row_weight[rows],
                    float(row_weight[rows].sum()),
                )
            )
        # Which cage vertices each handle drives in the first guess (the ones its surface leans on most).
        lean = (
            np.stack([np.asarray(self.C[rows].sum(0)).ravel() for rows in self._handle_rows])
            if self._handle_rows
            else np.zeros((0, n))
        )
        owner = np.where(lean.max(0) > 0, lean.argmax(0), -1) if len(lean) else np.full(n, -1)
        guess_regions = [np.flatnonzero(owner == h) for h in range(len(self._handle_rows))]
        held = np.flatnonzero(np.asarray(abs(self.C).sum(0)).ravel() > 0)
        still = np.setdiff1d(held, np.flatnonzero(owner >= 0))
        # The first guess blends the handles' affines over the cage vertices each drives, the other
        # held vertices at rest; a piece of the cage with no handle stays at rest.
        self._guess = PieceBlend(V, pieces, guess_regions + [still], [True] * len(guess_regions) + [False])
        try:
            self._lu = splu(self.A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1, options=dict(SymmetricMode=True))
        except RuntimeError as e:
            raise EngineError(f"the cage pose's system is singular ({e}); is the cage degenerate?") from e
        self.precompute_s = time.perf_counter() - t0

    # -- the energy ---------------------------------------------------------------------------
    def _pulls(self, transforms: list) -> tuple[np.ndarray, float]:
        """(b, c): the handles' pulls this frame as D.QD - 2 D.b + c (D = U - rest)."""
        if len(transforms) != len(self._handle_rows):
            raise EngineError(f"{len(transforms)} handle transforms for {len(self._handle_rows)} handles")
        b, c = np.zeros_like(self.rest), 0.0
        for (G, g, S, s, w), A in zip(self._pull, transforms):
            A = affine_matrix(A)
            M, a = A[:3, :3].T - np.eye(3), A[:3, 3]
            b += G @ M + np.outer(g, a)
            c += float(np.trace(M.T @ S @ M) + 2.0 * s @ (M @ a) + w * (a @ a))
        return b, c

    def _local(self, U: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(B, J, E_ARAP): ARAP's local step at U (the global step's right-hand side), det F per tet and
        the elements energy, in one pass over the tets."""
        U = np.ascontiguousarray(U)
        B, J = np.empty_like(U), np.empty(len(self.tets))
        e = self._elements
        energy = surface_arap_kernels.surface_local(U, self.tets, e.W, e.E, self._inv_det0, B, J)
        return B, J, energy

    def _evaluate(self, U: np.ndarray, pulls):
        """(E, J, B): the energy (inf when a tet has J <= 0), det F per tet, ARAP's right-hand side at U."""
        B, J, energy = self._local(U)
        if not (J > 0).all():
            return np.inf, J, None
        D, (b, c) = U - self.rest, pulls
        E = energy + float((D * (self.Q @ D - 2.0 * b)).sum()) + c
        E += self.kappa * float((self.vol0 * barrier(J, self.j)).sum())
        return E, J, B

    def _barrier_terms(self, U: np.ndarray, J: np.ndarray):
        """Tets below j, dJ/dU per corner (k, 4, 3), kappa vol b'(J) and kappa vol b''(J)."""
        act = np.flatnonzero(J < self.j)
        P = U[self.tets[act]]
        e1, e2, e3 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]
        g = np.empty((len(act), 4, 3))
        g[:, 1], g[:, 2], g[:, 3] = np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)
        g[:, 1:] /= 6.0 * self.vol0[act, None, None]  # d det / dU over the rest det (J = det / det0)
        g[:, 0] = -g[:, 1:].sum(1)
        d1, d2 = _barrier_d1_d2(J[act], self.j)
        w = self.kappa * self.vol0[act]
        return act, g, w * d1, w * d2

    # -- the step direction ---------------------------------------------------------------------
    def _solve_A(self, R: np.ndarray) -> np.ndarray:
        return 0.5 * self._lu.solve(R)  # (2 A)^-1 R

    def _direction(self, r: np.ndarray, act, g, d2) -> np.ndarray:
        """(2 A + sum_t d2_t g_t g_t^T)^-1 r."""
        if len(act) <= WOODBURY_TETS:
            return self._woodbury(r, act, g, d2)
        import scipy.sparse as sp
        from scipy.sparse.linalg import splu

        n = len(r)
        dof = (self.tets[act][:, :, None] + n * np.arange(3)[None, None, :]).reshape(len(act), 12)  # coordinate-major
        gg = g.reshape(len(act), 12)
        vals = d2[:, None, None] * gg[:, :, None] * gg[:, None, :]
        ii = np.broadcast_to(dof[:, :, None], vals.shape).ravel()
        jj = np.broadcast_to(dof[:, None, :], vals.shape).ravel()
        H = (
            sp.kron(sp.identity(3), 2.0 * self.A) + sp.coo_matrix((vals.ravel(), (ii, jj)), shape=(3 * n, 3 * n))
        ).tocsc()
        lu = splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1, options=dict(SymmetricMode=True))
        return lu.solve(r.T.ravel()).reshape(3, n).T

    def _woodbury(self, r: np.ndarray, act, g, d2) -> np.ndarray:
        """(2A + Z Z^T)^-1 r, Z = [sqrt(d2_t) g_t]: the columns of (2A)^-1 at the active tets' vertices
        are kept for the rest of this solve (A does not change; not across solves, so a frame's
        result does not depend on the frames before)."""
        x = self._solve_A(r)
        if not len(act):
            return x
        k = len(act)
        verts, local = np.unique(self.tets[act], return_inverse=True)
        local = local.reshape(k, 4)
        missing = [v for v in verts.tolist() if v not in self._columns]
        if missing:
            unit = np.zeros((len(r), len(missing)))
            unit[missing, np.arange(len(missing))] = 1.0
            for v, col in zip(missing, self._solve_A(unit).T):
                self._columns[v] = col
        W = np.stack([self._columns[v] for v in verts.tolist()], axis=1)  # (n, nv)
        s = np.sqrt(np.maximum(d2, 0.0))
        S = np.zeros((3, len(verts), k))
        cols = np.arange(k)
        for c in range(4):
            for a in range(3):
                np.add.at(S[a], (local[:, c], cols), s * g[:, c, a])
        Wv = W[verts]
        M = np.eye(k) + sum(S[a].T @ Wv @ S[a] for a in range(3))
        y = np.linalg.solve(M, sum(S[a].T @ x[verts, a] for a in range(3)))
        return x - W @ np.stack([S[a] @ y for a in range(3)], axis=1)

    def _lbfgs(self, G: np.ndarray, history: list, act, g, d2) -> np.ndarray:
        """The L-BFGS direction: the two-loop recursion around the quasi-Newton matrix's inverse."""
        q, alphas = G.copy(), []
        for s_k, y_k, rho in reversed(history):
            a = rho * float((s_k * q).sum())
            q -= a * y_k
            alphas.append(a)
        r = self._direction(q, act, g, d2)
        for (s_k, y_k, rho), a in zip(history, reversed(alphas)):
            r += s_k * (a - rho * float((y_k * r).sum()))
        return -r

    # -- the solve ----------------------------------------------------------------------------
    def _first_guess(self, transforms: list, pulls) -> np.ndarray:
        """A flip-free start from the pose alone: the linear blend of the handles' affines (pins at rest),
        per piece of the cage. Where it squeezes a tet below j (the blend of two turns collapses a bend's
        inside), plain ARAP steps from it, the barrier left out: on the demo's bends one step undoes every
        fold and leaves every tet above j, where the barrier would only slow the solve down. The first of
        these with every tet above j, else the last with every tet above j / 2, else the last pulled back
        towards the rest cage until every tet keeps J >= j / 2."""
        U = self._guess([affine_matrix(A) for A in transforms] + [np.eye(4)])
        clear = None
        for step in range(GUESS_STEPS + 1):
            B, J, _ = self._local(U)
            if J.min() >= self.j:
                return U
            if J.min() >= 0.5 * self.j:
                clear = U
            if step < GUESS_STEPS:
                U = self.rest + self._solve_A(
                    2.0 * (B - self._L_rest + pulls[0])
                )  # the minimiser of E at these rotations
        if clear is not None:
            return clear
        D = U - self.rest
        lo, hi = 0.0, 1.0
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            ok = (signed_volumes(self.rest + mid * D, self.tets) >= 0.5 * self.j * self.vol0).all()
            lo, hi = (mid, hi) if ok else (lo, mid)
        return self.rest + lo * D

    def solve(self, transforms: list, max_iter: int = 100, tol: float = 1e-4) -> SurfacePose:
        """The cage posed by one 4x4 affine per handle (NeRF frame). Stops when a step moves no vertex
        more than `tol` x the cage's diagonal, after at most `max_iter` iterations."""
        t0 = time.perf_counter()
        pulls = self._pulls(transforms)
        U = self._first_guess(transforms, pulls)
        E, J, B = self._evaluate(U, pulls)
        if not np.isfinite(E):
            raise EngineError("internal: the cage pose started from a configuration with an inverted tet")
        self._columns = {}
        it, moved = 0, np.inf
        history, last = [], None  # L-BFGS pairs (s, y, 1 / s.y); the previous iterate and gradient
        for it in range(1, max_iter + 1):  # noqa: B007 (the iterations run: the result reports `it`)
            G = 2.0 * (self.L @ U - B) + 2.0 * (self.Q @ (U - self.rest) - pulls[0])
            act, g, d1, d2 = self._barrier_terms(U, J)
            if len(act):
                np.add.at(G, self.tets[act].ravel(), (d1[:, None, None] * g).reshape(-1, 3))
                history, last = [], None  # the barrier's curvature changes too fast for secant pairs: plain steps
            if last is not None:
                s_k, y_k = U - last[0], G - last[1]
                sy = float((s_k * y_k).sum())
                if sy > 1e-12 * float((y_k * y_k).sum()) ** 0.5 * float((s_k * s_k).sum()) ** 0.5:
                    history = (history + [(s_k, y_k, 1.0 / sy)])[max(0, len(history) + 1 - HISTORY) :]
            d = self._lbfgs(G, history, act, g, d2)
            slope = float((G * d).sum())
            if slope >= 0 and history:  # the history's curvature misleads: start over from the plain step
                history = []
                d = self._lbfgs(G, history, act, g, d2)
                slope = float((G * d).sum())
            full = float(np.abs(d).max()) / self.diag
            if slope >= 0 or full < 1e-3 * tol:  # no descent left, or nothing left to move (round-off)
                moved = full
                break
            alpha = 1.0
            while True:
                trial = U + alpha * d
                E_t, J_t, B_t = self._evaluate(trial, pulls)
                if E_t <= E + 1e-4 * alpha * slope:  # an inverted trial has E_t = inf: refused
                    break
                alpha *= 0.5
                if alpha < 1e-12:
                    break
            if alpha < 1e-12:
                moved = 0.0
                break
            moved = alpha * full
            last = (U, G)
            U, E, J, B = trial, E_t, J_t, B_t
            if moved < tol:
                break
        residual = 0.0
        for rows, C_h, size, A in zip(self._handle_rows, self._handle_C, self._region_size, transforms):
            A = affine_matrix(A)
            target = self._rest_points[rows] @ A[:3, :3].T + A[:3, 3]
            residual = max(residual, float(np.linalg.norm(C_h @ U - target, axis=1).max()) / size)
        reflected = [name for name, A in zip(self.names, transforms) if np.linalg.det(affine_matrix(A)[:3, :3]) < 0]
        return SurfacePose(
            U, it, moved < tol, time.perf_counter() - t0, float(J.min()), residual, int((J < self.j).sum()), reflected
        )
