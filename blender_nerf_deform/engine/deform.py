"""Deformers of the cage: an affine transform of a region, and ARAP from handles.

Regions are chosen on the extracted mesh (the artist selects its vertices in
Blender) and mapped to cage vertices through the surface embedding: the cage
vertices that carry the selected surface vertices' barycentric weights.

ARAP (elements energy on tets, libigl's cotangent weights; our local/global
iteration with numba kernels and a prefactored sparse LU, or libigl's
`arap_precomputation` / `arap_solve` as the reference and for the spokes
energies): precomputed once per set of handles and pins, then solved per
frame for the handles' target affines (location, rotation, scale of their
Empties). Two ways to solve:
- `solve(transforms)`: iterate from a deterministic start (the rest cage, or
  `initial`) until the largest vertex step falls below `tol` x the cage's
  diagonal, at most `max_iter` iterations. A frame's result then depends only
  on that frame's handles, as a render farm needs.
- `step(transforms, iterations=1)`: warm-started from the previous result, a
  fixed number of iterations: the interactive preview (one iteration per
  handle move converges over successive moves).
Neither hangs: both are bounded by their iteration count; a non-finite result
raises, and a solve that did not reach `tol` says so in its result (or raises
with `strict=True`)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .errors import EngineError


def _matrix(A) -> np.ndarray:
    A = np.asarray(A, dtype=np.float64)
    if A.shape == (3, 4):
        A = np.vstack([A, [0, 0, 0, 1]])
    if A.shape != (4, 4):
        raise EngineError(f"a transform must be a 4x4 (or 3x4) matrix, got shape {A.shape}")
    if not np.isfinite(A).all():
        raise EngineError("a transform has non-finite entries")
    return A


def apply_affine(points: np.ndarray, A) -> np.ndarray:
    A = _matrix(A)
    return np.asarray(points, dtype=np.float64) @ A[:3, :3].T + A[:3, 3]


def affine_region(vertices: np.ndarray, region: np.ndarray, A) -> np.ndarray:
    """Cage vertices with those of `region` (indices or boolean mask) moved by the affine A; others unchanged."""
    V = np.array(vertices, dtype=np.float64, copy=True)
    idx = _indices(region, len(V), "region")
    if len(idx) == 0:
        raise EngineError("the region to transform has no vertices")
    V[idx] = apply_affine(V[idx], A)
    return V


def _indices(region, n: int, name: str) -> np.ndarray:
    r = np.asarray(region)
    if r.dtype == bool:
        if r.shape != (n,):
            raise EngineError(f"{name}: a boolean mask must have one entry per vertex ({n}), got {r.shape}")
        return np.flatnonzero(r)
    r = r.astype(np.int64).ravel()
    if r.size and (r.min() < 0 or r.max() >= n):
        raise EngineError(f"{name} indexes vertices outside 0..{n - 1}")
    return np.unique(r)


def check_disjoint(regions: list, n: int, names: list[str]) -> list[np.ndarray]:
    """Index arrays of the regions; EngineError if one is empty or two share a vertex."""
    out = [_indices(r, n, name) for r, name in zip(regions, names)]
    for r, name in zip(out, names):
        if len(r) == 0:
            raise EngineError(f"{name} has no vertices")
    owner = np.full(n, -1)
    for i, r in enumerate(out):
        clash = owner[r]
        if (clash >= 0).any():
            j = int(clash[clash >= 0][0])
            raise EngineError(f"{names[j]} and {names[i]} overlap: they share {(clash >= 0).sum()} vertices")
        owner[r] = i
    return out


def regions_to_cage(embedding, surface_regions: list, n_cage_vertices: int, names: list[str] | None = None) -> list[np.ndarray]:
    """Map regions of the extracted mesh's vertices to regions of cage vertices.

    A cage vertex joins a region when that region's selected surface vertices
    put barycentric weight on it; a cage vertex claimed by several regions goes
    to the one that puts the most weight on it. Errors for an empty region,
    overlapping surface selections, or a region left with no cage vertex.
    """
    n_surface = len(embedding.weights)
    names = names or [f"handle region {i}" for i in range(len(surface_regions))]
    regs = check_disjoint(surface_regions, n_surface, names)
    W = np.stack([embedding.cage_vertex_weights(r, n_cage_vertices) for r in regs])  # (R, n_cage)
    best = W.argmax(0)
    out = []
    for i, name in enumerate(names):
        cage_idx = np.flatnonzero((W[i] > 1e-9) & (best == i))
        if len(cage_idx) == 0:
            raise EngineError(f"{name} maps to no cage vertex (its surface vertices are claimed by other regions)")
        out.append(cage_idx)
    return out


def linear_blend(rest_vertices: np.ndarray, regions: list, transforms: list, power: float = 2.0) -> np.ndarray:
    """Baseline deformer: each vertex blends the regions' affines by inverse distance to each region.

    What ARAP is compared against (the seed's cube check); not used for editing.
    """
    from scipy.spatial import cKDTree

    V = np.asarray(rest_vertices, dtype=np.float64)
    regs = check_disjoint(regions, len(V), [f"region {i}" for i in range(len(regions))])
    d = np.stack([cKDTree(V[r]).query(V)[0] for r in regs])  # (R, N)
    w = 1.0 / np.maximum(d, 1e-12) ** power
    for i, r in enumerate(regs):
        w[:, r] = 0.0
        w[i, r] = 1.0
    w /= w.sum(0, keepdims=True)
    moved = np.stack([apply_affine(V, A) for A in transforms])  # (R, N, 3)
    return np.einsum("rn,rnc->nc", w, moved)


# ---------------------------------------------------------------------------
# ARAP: our own local/global iteration (elements energy on tets).
#
# Why not igl.arap_solve per frame: each call pays libigl's generic per-solve
# work (covariance scatter, a 3x3 SVD per tet, the right-hand side through
# sparse products, mostly on one core): ~130 ms per iteration on a 22k-vertex
# / 118k-tet cage on 2 cores, over the 100 ms per frame we allow. Here the
# local step (covariance, best rotation and right-hand side of every tet) is
# one fused parallel numba kernel (~23 ms there), and the global step reuses a
# sparse LU (scipy's SuperLU, symmetric ordering) of the constrained cotangent
# Laplacian, factored once per set of handles (~24 ms for 3 right-hand sides).
# Same energy and weights as libigl's ARAP_ENERGY_TYPE_ELEMENTS (its
# `cotmatrix_entries`), so both converge to the same deformation;
# tools/bench_geometry_arap.py runs them side by side.
# ---------------------------------------------------------------------------

# Edges of a tet in the column order of igl.cotmatrix_entries.
_TET_EDGES = np.array([[1, 2], [2, 0], [0, 1], [3, 0], [3, 1], [3, 2]], dtype=np.int64)
_E0 = _TET_EDGES[:, 0].copy()  # module constants, frozen into the kernels
_E1 = _TET_EDGES[:, 1].copy()

try:  # numba is an optional accelerator, pinned in requirements.txt; without it ARAP runs libigl's solver.
    from numba import njit, prange

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    HAVE_NUMBA = False


if HAVE_NUMBA:

    @njit(inline="always")
    def _jacobi_top_eigenvector(A, Q):
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
    def _arap_local(U, T, W, E, corner_rhs, energy):
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
                for a in range(3):
                    for b in range(3):
                        S[a, b] = 0.0
                for e in range(6):
                    i = T[t, _E0[e]]
                    j = T[t, _E1[e]]
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
                k = _jacobi_top_eigenvector(A, Q)
                q0, q1, q2, q3 = Q[0, k], Q[1, k], Q[2, k], Q[3, k]
                nq = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
                q0, q1, q2, q3 = q0 / np.sqrt(nq), q1 / np.sqrt(nq), q2 / np.sqrt(nq), q3 / np.sqrt(nq)
                R[0, 0] = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
                R[0, 1] = 2.0 * (q1 * q2 - q0 * q3)
                R[0, 2] = 2.0 * (q1 * q3 + q0 * q2)
                R[1, 0] = 2.0 * (q1 * q2 + q0 * q3)
                R[1, 1] = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3
                R[1, 2] = 2.0 * (q2 * q3 - q0 * q1)
                R[2, 0] = 2.0 * (q1 * q3 - q0 * q2)
                R[2, 1] = 2.0 * (q2 * q3 + q0 * q1)
                R[2, 2] = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3
                for c in range(4):
                    for a in range(3):
                        corner_rhs[t, c, a] = 0.0
                en = 0.0
                for e in range(6):
                    ci, cj = _E0[e], _E1[e]
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
    def _gather_rhs(corner_rhs, start, slots, B):
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


@dataclass
class ArapResult:
    vertices: np.ndarray
    iterations: int
    last_step: float  # largest vertex move of the last iteration, relative to the cage's diagonal
    converged: bool
    seconds: float


class ArapDeformer:
    """ARAP on the cage's tets with handle regions (each moved by an affine) and pinned regions.

    backend: "numba" (our local/global iteration above; elements energy only),
    "igl" (libigl's arap_precomputation / arap_solve, any energy: the reference
    the benchmark compares against), or "auto" (numba for the elements energy
    where numba is installed, else igl).
    """

    ENERGIES = ("elements", "spokes", "spokes_and_rims")

    def __init__(self, rest_vertices: np.ndarray, tets: np.ndarray, handles: list, pins: list | None = None, energy: str = "elements", backend: str = "auto"):
        V = np.ascontiguousarray(rest_vertices, dtype=np.float64)
        T = np.ascontiguousarray(tets, dtype=np.int64)
        pins = list(pins or [])
        if not handles and not pins:
            raise EngineError("ARAP needs at least one handle or pinned region")
        names = [f"handle region {i}" for i in range(len(handles))] + [f"pinned region {i}" for i in range(len(pins))]
        regs = check_disjoint(list(handles) + pins, len(V), names)
        self.handles, self.pins = regs[: len(handles)], regs[len(handles) :]
        self.rest, self.tets = V, T
        self.diag = float(np.linalg.norm(np.ptp(V, axis=0)))
        self.b = np.concatenate(regs).astype(np.int64)
        if energy not in self.ENERGIES:
            raise EngineError(f"unknown ARAP energy {energy!r}; one of {sorted(self.ENERGIES)}")
        if backend == "auto":
            backend = "numba" if (energy == "elements" and HAVE_NUMBA) else "igl"
        if backend == "numba" and (energy != "elements" or not HAVE_NUMBA):
            raise EngineError("the numba ARAP backend needs numba and runs the elements energy only")
        if backend not in ("numba", "igl"):
            raise EngineError(f"unknown ARAP backend {backend!r}; one of auto, numba, igl")
        self.backend, self.energy_type = backend, energy
        t0 = time.perf_counter()
        if backend == "igl":
            import igl

            self._igl = igl
            self.data = igl.ARAPData()
            self.data.energy = {
                "elements": igl.ARAP_ENERGY_TYPE_ELEMENTS,
                "spokes": igl.ARAP_ENERGY_TYPE_SPOKES,
                "spokes_and_rims": igl.ARAP_ENERGY_TYPE_SPOKES_AND_RIMS,
            }[energy]
            self.data.max_iter = 1
            igl.arap_precomputation(V, T, 3, self.b.astype(np.int32), self.data)
        else:
            self._precompute()
        self.precompute_s = time.perf_counter() - t0
        self.U: np.ndarray | None = None  # last result (warm start of `step`)

    def _precompute(self):
        """Cotangent weights per tet edge, rest edge vectors, and the LU of the constrained system."""
        import igl
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components
        from scipy.sparse.linalg import splu

        V, T, n = self.rest, self.tets, len(self.rest)
        self._W = np.ascontiguousarray(igl.cotmatrix_entries(V, T), dtype=np.float64)  # (M, 6)
        self._E = np.ascontiguousarray(V[T[:, _E0]] - V[T[:, _E1]])  # (M, 6, 3) rest edge vectors
        # The energy's quadratic form sum w |u_i - u_j|^2 (= -igl.cotmatrix), assembled from the same weights.
        i, j, w = T[:, _E0].ravel(), T[:, _E1].ravel(), self._W.ravel()
        L = sp.coo_matrix((np.concatenate([-w, -w, w, w]), (np.concatenate([i, j, i, j]), np.concatenate([j, i, i, j]))), shape=(n, n)).tocsr()
        constrained = np.zeros(n, dtype=bool)
        constrained[self.b] = True
        self._free = np.flatnonzero(~constrained)
        Lf = L[self._free]
        self._Lfb = Lf[:, self.b].tocsr()
        # Every connected part of the cage needs a handle or pin, else its position is undetermined.
        n_parts, part = connected_components(L, directed=False)
        loose = np.setdiff1d(np.arange(n_parts), part[self.b])
        if len(loose):
            raise EngineError(f"ARAP: {len(loose)} connected part(s) of the cage ({int(np.isin(part, loose).sum())} vertices) hold no handle or pinned vertex")
        self._lu = None
        if len(self._free):
            try:
                # Symmetric positive definite: a symmetric fill-reducing ordering and diagonal
                # pivots keep the factors about half the size of SuperLU's default (COLAMD).
                self._lu = splu(Lf[:, self._free].tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1, options=dict(SymmetricMode=True))
            except RuntimeError as e:
                raise EngineError(f"ARAP system is singular ({e}); is the cage degenerate?") from e
        # Which (tet, corner) slots touch each vertex, to gather the right-hand side in parallel.
        self._slots = np.argsort(T.ravel(), kind="stable")
        self._start = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(T.ravel(), minlength=n), out=self._start[1:])
        self._corner = np.empty((len(T), 4, 3))
        self._tet_energy = np.empty(len(T))
        self._B = np.empty((n, 3))

    def _local(self, U: np.ndarray) -> None:
        _arap_local(U, self.tets, self._W, self._E, self._corner, self._tet_energy)

    def energy(self, vertices: np.ndarray) -> float:
        """ARAP (elements) energy of `vertices`: sum over tets and edges of w |u_i - u_j - R_t (v_i - v_j)|^2
        with each tet's best rotation R_t (0 for a rigid motion). Needs the numba backend."""
        if self.backend != "numba":
            raise EngineError("ARAP energy is computed by the numba backend")
        self._local(np.ascontiguousarray(vertices, dtype=np.float64))
        return float(self._tet_energy.sum())

    def constraints(self, transforms: list) -> np.ndarray:
        """Target positions of the constrained vertices (handles moved by their affines, pins at rest)."""
        if len(transforms) != len(self.handles):
            raise EngineError(f"ARAP has {len(self.handles)} handle regions but got {len(transforms)} transforms")
        parts = [apply_affine(self.rest[h], A) for h, A in zip(self.handles, transforms)]
        parts += [self.rest[p] for p in self.pins]
        return np.ascontiguousarray(np.concatenate(parts) if parts else np.zeros((0, 3)))

    def _one_iteration(self, bc: np.ndarray, U: np.ndarray, fixed_rhs) -> np.ndarray:
        if self.backend == "igl":
            return self._igl.arap_solve(bc, self.data, U)
        self._local(U)  # best rotation per tet for U, and the right-hand side it implies
        _gather_rhs(self._corner, self._start, self._slots, self._B)
        U_new = np.empty_like(U)
        U_new[self.b] = bc
        if self._lu is not None:
            U_new[self._free] = self._lu.solve(self._B[self._free] - fixed_rhs)
        return U_new

    def _iterate(self, bc: np.ndarray, U: np.ndarray, iterations: int, tol: float | None):
        step = np.inf
        it = 0
        fixed_rhs = self._Lfb @ bc if self.backend == "numba" else None  # the constrained vertices' pull on the free ones
        for it in range(1, iterations + 1):
            U_new = self._one_iteration(bc, U, fixed_rhs)
            if not np.isfinite(U_new).all():
                raise EngineError(f"ARAP diverged (non-finite positions after {it} iterations); check the handles' transforms")
            step = float(np.abs(U_new - U).max()) / self.diag
            U = U_new
            if tol is not None and step < tol:
                break
        return U, it, step

    def solve(self, transforms: list, max_iter: int = 50, tol: float = 1e-4, initial: np.ndarray | None = None, strict: bool = False) -> ArapResult:
        """Iterate from `initial` (default: the linear blend of the handles' affines, a deterministic
        start that is already right for rigid motions) until converged or `max_iter` iterations."""
        t0 = time.perf_counter()
        bc = self.constraints(transforms)
        if initial is None:
            regions = self.handles + self.pins
            mats = [_matrix(A) for A in transforms] + [np.eye(4)] * len(self.pins)
            initial = linear_blend(self.rest, regions, mats)
        U = np.array(initial, dtype=np.float64)
        U[self.b] = bc
        U, it, step = self._iterate(bc, U, max_iter, tol)
        res = ArapResult(U, it, step, step < tol, time.perf_counter() - t0)
        if strict and not res.converged:
            raise EngineError(f"ARAP did not converge in {max_iter} iterations (last step {step:.2e} of the cage's size, tolerance {tol:.0e})")
        self.U = U
        return res

    def step(self, transforms: list, iterations: int = 1) -> ArapResult:
        """A fixed number of iterations warm-started from the previous result (interactive preview)."""
        t0 = time.perf_counter()
        bc = self.constraints(transforms)
        U = np.array(self.rest if self.U is None else self.U, dtype=np.float64)
        U[self.b] = bc
        U, it, step = self._iterate(bc, U, iterations, None)
        self.U = U
        return ArapResult(U, it, step, False, time.perf_counter() - t0)


def edge_length_distortion(rest_vertices: np.ndarray, deformed_vertices: np.ndarray, tets: np.ndarray) -> float:
    """Mean relative change of the tet edge lengths (0 = rigid)."""
    T = np.asarray(tets)
    e = np.concatenate([T[:, [i, j]] for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
    e = np.unique(np.sort(e, axis=1), axis=0)
    l0 = np.linalg.norm(rest_vertices[e[:, 0]] - rest_vertices[e[:, 1]], axis=1)
    l1 = np.linalg.norm(deformed_vertices[e[:, 0]] - deformed_vertices[e[:, 1]], axis=1)
    return float(np.mean(np.abs(l1 - l0) / l0))
