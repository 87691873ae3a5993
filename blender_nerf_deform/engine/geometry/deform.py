"""Deformers of the cage: an affine transform of a region, and ARAP with its handles on cage vertices.

Regions are chosen on the extracted mesh (the artist selects its vertices in
Blender) and mapped to cage vertices through the surface embedding: the cage
vertices that carry the selected surface vertices' barycentric weights.

The add-on's poses come from handle_pose.RegionDeformer: Affine Regions with the
affines here, ARAP with surface_arap.SurfaceArap (the handles pull the surface, and
no tet can invert). `ArapDeformer` below pins cage vertices to their targets (hard
constraints): the reference for the kernels both share (against libigl's
arap_solve, tools/bench/geometry_arap.py) and what poses came from before.

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

from .. import backend as code_path
from ..errors import EngineError
from . import arap_kernels
from .arap_kernels import EDGE_END, EDGE_START


def affine_matrix(A) -> np.ndarray:
    A = np.asarray(A, dtype=np.float64)
    if A.shape == (3, 4):
        A = np.vstack([A, [0, 0, 0, 1]])
    if A.shape != (4, 4):
        raise EngineError(f"a transform must be a 4x4 (or 3x4) matrix, got shape {A.shape}")
    if not np.isfinite(A).all():
        raise EngineError("a transform has non-finite entries")
    return A


def apply_affine(points: np.ndarray, A) -> np.ndarray:
    A = affine_matrix(A)
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


def regions_to_cage(
    embedding, surface_regions: list, n_cage_vertices: int, names: list[str] | None = None
) -> list[np.ndarray]:
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


def blend_weights(rest_vertices: np.ndarray, regions: list, power: float = 2.0) -> np.ndarray:
    """(R, N) weights of the linear blend: each vertex weighs the regions by inverse distance to each
    (a region's own vertices take its affine alone); columns sum to 1. Depends on the regions only."""
    from scipy.spatial import cKDTree

    V = np.asarray(rest_vertices, dtype=np.float64)
    regs = check_disjoint(regions, len(V), [f"region {i}" for i in range(len(regions))])
    d = np.stack([cKDTree(V[r]).query(V)[0] for r in regs])  # (R, N)
    w = 1.0 / np.maximum(d, 1e-12) ** power
    for i, r in enumerate(regs):
        w[:, r] = 0.0
        w[i, r] = 1.0
    return w / w.sum(0, keepdims=True)


def blend(rest_vertices: np.ndarray, weights: np.ndarray, transforms: list) -> np.ndarray:
    """The vertices moved by the affines blended with `blend_weights`."""
    moved = np.stack([apply_affine(rest_vertices, A) for A in transforms])  # (R, N, 3)
    return np.einsum("rn,rnc->nc", weights, moved)


class PieceBlend:
    """The linear blend of the regions' affines, piece by piece of the cage: a piece (one object of
    several edit regions) blends only the regions that lie on it, so a handle on one object does not
    start another one off its rest. The weights depend on the regions only, so they are made once;
    a piece none of whose regions is `moving` (pins only) is left exactly at rest."""

    def __init__(self, rest_vertices: np.ndarray, pieces: np.ndarray, regions: list, moving: list | None = None):
        self.rest = np.asarray(rest_vertices, dtype=np.float64)
        moving = [True] * len(regions) if moving is None else list(moving)
        self._pieces = []  # (its vertices, blend weights, which region's affine each weight row takes)
        for piece in np.unique(pieces):
            own = np.flatnonzero(pieces == piece)
            local = np.full(len(self.rest), -1, dtype=np.int64)
            local[own] = np.arange(len(own))
            mine = [(local[r[pieces[r] == piece]], k) for k, r in enumerate(regions)]
            mine = [(r, k) for r, k in mine if len(r)]
            if any(moving[k] for _, k in mine):
                self._pieces.append((own, blend_weights(self.rest[own], [r for r, _ in mine]), [k for _, k in mine]))

    def __call__(self, transforms: list) -> np.ndarray:
        """The blended vertices for one 4x4 affine per region."""
        out = np.array(self.rest, copy=True)
        for own, weights, which in self._pieces:
            out[own] = blend(self.rest[own], weights, [transforms[k] for k in which])
        return out


def linear_blend(rest_vertices: np.ndarray, regions: list, transforms: list, power: float = 2.0) -> np.ndarray:
    """Baseline deformer: each vertex blends the regions' affines by inverse distance to each region.

    What ARAP is compared against (the seed's cube check), and ARAP's first guess."""
    return blend(rest_vertices, blend_weights(rest_vertices, regions, power), transforms)


# ---------------------------------------------------------------------------
# ARAP: our own local/global iteration (elements energy on tets).
#
# Why not igl.arap_solve per frame: each call pays libigl's generic per-solve
# work (covariance scatter, a 3x3 SVD per tet, the right-hand side through
# sparse products, mostly on one core), more than a frame allows on a demo-sized
# cage. Here the local step (covariance, best rotation and right-hand side of
# every tet) is one fused parallel numba kernel, and the global step reuses a
# sparse LU (scipy's SuperLU, symmetric ordering) of the constrained cotangent
# Laplacian, factored once per set of handles.
# Same energy and weights as libigl's ARAP_ENERGY_TYPE_ELEMENTS (its
# `cotmatrix_entries`), so both converge to the same deformation;
# tools/bench/geometry_arap.py runs them side by side.
# ---------------------------------------------------------------------------


class ElementsEnergy:
    """ARAP's elements energy on a tet mesh, what both solvers share (ArapDeformer here,
    surface_arap.SurfaceArap): libigl's cotangent weights per tet edge, the rest edge vectors, the
    energy's quadratic form L = sum w |u_i - u_j|^2 (= -igl.cotmatrix), and which (tet, corner) slots
    touch each vertex, so the right-hand side is gathered per vertex in parallel."""

    def __init__(self, vertices: np.ndarray, tets: np.ndarray):
        import igl
        import scipy.sparse as sp

        V, T, n = vertices, tets, len(vertices)
        self.tets = T
        self.W = np.ascontiguousarray(igl.cotmatrix_entries(V, T), dtype=np.float64)  # (M, 6)
        self.E = np.ascontiguousarray(V[T[:, EDGE_START]] - V[T[:, EDGE_END]])  # (M, 6, 3) rest edge vectors
        i, j, w = T[:, EDGE_START].ravel(), T[:, EDGE_END].ravel(), self.W.ravel()
        self.L = sp.coo_matrix(
            (np.concatenate([-w, -w, w, w]), (np.concatenate([i, j, i, j]), np.concatenate([j, i, i, j]))), shape=(n, n)
        ).tocsr()
        self.slots = np.argsort(T.ravel(), kind="stable")
        self.slot_start = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(T.ravel(), minlength=n), out=self.slot_start[1:])
        self.corner = np.empty((len(T), 4, 3))
        self.tet_energy = np.empty(len(T))  # per tet, at the last `local` call

    def local(self, U: np.ndarray, rhs: np.ndarray | None = None) -> np.ndarray:
        """The local step at U (C-contiguous float64): each tet's best rotation and energy
        (`tet_energy`), and the global step's right-hand side it implies (into `rhs` when given)."""
        arap_kernels.arap_local(U, self.tets, self.W, self.E, self.corner, self.tet_energy)
        rhs = np.empty_like(U) if rhs is None else rhs
        arap_kernels.gather_rhs(self.corner, self.slot_start, self.slots, rhs)
        return rhs


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

    def __init__(
        self,
        rest_vertices: np.ndarray,
        tets: np.ndarray,
        handles: list,
        pins: list | None = None,
        energy: str = "elements",
        backend: str = "auto",
    ):
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
            backend = "numba" if (energy == "elements" and code_path.use_kernels("cpu")) else "igl"
        if backend == "numba" and (energy != "elements" or not code_path.HAVE_NUMBA):
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
        """The elements energy's pieces, and the LU of the constrained system."""
        from scipy.sparse.csgraph import connected_components
        from scipy.sparse.linalg import splu

        n = len(self.rest)
        self._elements = ElementsEnergy(self.rest, self.tets)
        L = self._elements.L
        constrained = np.zeros(n, dtype=bool)
        constrained[self.b] = True
        self._free = np.flatnonzero(~constrained)
        Lf = L[self._free]
        self._Lfb = Lf[:, self.b].tocsr()
        # Every connected part of the cage needs a handle or pin, else its position is undetermined.
        n_parts, part = connected_components(L, directed=False)
        loose = np.setdiff1d(np.arange(n_parts), part[self.b])
        if len(loose):
            raise EngineError(
                f"ARAP: {len(loose)} connected part(s) of the cage ({int(np.isin(part, loose).sum())} vertices) "
                "hold no handle or pinned vertex"
            )
        self._lu = None
        if len(self._free):
            try:
                # Symmetric positive definite: a symmetric fill-reducing ordering and diagonal
                # pivots keep the factors about half the size of SuperLU's default (COLAMD).
                self._lu = splu(
                    Lf[:, self._free].tocsc(),
                    permc_spec="MMD_AT_PLUS_A",
                    diag_pivot_thresh=0.1,
                    options=dict(SymmetricMode=True),
                )
            except RuntimeError as e:
                raise EngineError(f"ARAP system is singular ({e}); is the cage degenerate?") from e
        self._B = np.empty((n, 3))

    def energy(self, vertices: np.ndarray) -> float:
        """ARAP (elements) energy of `vertices`: sum over tets and edges of w |u_i - u_j - R_t (v_i - v_j)|^2
        with each tet's best rotation R_t (0 for a rigid motion). Needs the numba backend."""
        if self.backend != "numba":
            raise EngineError("ARAP energy is computed by the numba backend")
        self._elements.local(np.ascontiguousarray(vertices, dtype=np.float64))
        return float(self._elements.tet_energy.sum())

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
        self._elements.local(U, self._B)  # best rotation per tet for U, and the right-hand side it implies
        U_new = np.empty_like(U)
        U_new[self.b] = bc
        if self._lu is not None:
            U_new[self._free] = self._lu.solve(self._B[self._free] - fixed_rhs)
        return U_new

    def _iterate(self, bc: np.ndarray, U: np.ndarray, iterations: int, tol: float | None):
        step = np.inf
        it = 0
        fixed_rhs = (
            self._Lfb @ bc if self.backend == "numba" else None
        )  # the constrained vertices' pull on the free ones
        for it in range(1, iterations + 1):
            U_new = self._one_iteration(bc, U, fixed_rhs)
            if not np.isfinite(U_new).all():
                raise EngineError(
                    f"ARAP diverged (non-finite positions after {it} iterations); check the handles' transforms"
                )
            step = float(np.abs(U_new - U).max()) / self.diag
            U = U_new
            if tol is not None and step < tol:
                break
        return U, it, step

    def _blended_start(self, transforms: list) -> np.ndarray:
        """The linear blend of the handles' and pins' affines, piece by piece of the cage (PieceBlend)."""
        if getattr(self, "_blend", None) is None:
            self._blend = PieceBlend(self.rest, tet_components(len(self.rest), self.tets), self.handles + self.pins)
        return self._blend([affine_matrix(A) for A in transforms] + [np.eye(4)] * len(self.pins))

    def solve(
        self,
        transforms: list,
        max_iter: int = 50,
        tol: float = 1e-4,
        initial: np.ndarray | None = None,
        strict: bool = False,
    ) -> ArapResult:
        """Iterate from `initial` (default: the linear blend of the handles' affines, a deterministic
        start that is already right for rigid motions) until converged or `max_iter` iterations.
        Hard constraints know nothing of orientation: a strong bend on a coarse cage can invert
        tets. The add-on's poses use surface_arap.SurfaceArap, which cannot."""
        t0 = time.perf_counter()
        bc = self.constraints(transforms)
        if initial is None:
            initial = self._blended_start(transforms)
        U = np.array(initial, dtype=np.float64)
        U[self.b] = bc
        U, it, step = self._iterate(bc, U, max_iter, tol)
        if strict and step >= tol:
            raise EngineError(
                f"ARAP did not converge in {max_iter} iterations (last step {step:.2e} of the cage's size, "
                f"tolerance {tol:.0e})"
            )
        res = ArapResult(U, it, step, step < tol, time.perf_counter() - t0)
        self.U = U
        return res

    def step(self, transforms: list, iterations: int = 1) -> ArapResult:
        """A fixed number of iterations warm-started from the previous result."""
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


def split_regions(index: np.ndarray, counts: np.ndarray) -> list[np.ndarray]:
    """Regions sent concatenated (`index`) with their sizes (`counts`) → one index array per region."""
    index, counts = np.asarray(index, dtype=np.int64), np.asarray(counts, dtype=np.int64)
    if counts.ndim != 1 or (counts < 0).any() or counts.sum() != len(index):
        raise EngineError(f"region sizes {counts.tolist()} do not add up to the {len(index)} region indices given")
    return np.split(index, np.cumsum(counts)[:-1]) if len(counts) else []


def tet_components(n_vertices: int, tets: np.ndarray) -> np.ndarray:
    """Connected piece of each vertex of a tet mesh (labels 0..k-1; scipy's graph components)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    T = np.asarray(tets, dtype=np.int64)
    edges = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 3]]])
    graph = coo_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)[1]
