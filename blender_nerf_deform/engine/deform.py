"""Deformers of the cage: an affine transform of a region, and ARAP from handles (libigl).

Regions are chosen on the extracted mesh (the artist selects its vertices in
Blender) and mapped to cage vertices through the surface embedding: the cage
vertices that carry the selected surface vertices' barycentric weights.

ARAP (libigl `arap_precomputation` / `arap_solve`, elements energy on tets):
precomputed once per set of handles and pins, then solved per frame for the
handles' target affines (location, rotation, scale of their Empties). Two ways
to solve:
- `solve(transforms)`: iterate from a deterministic start (the rest cage, or
  `initial`) until the largest vertex step falls below `tol` x the cage's
  diagonal, at most `max_iter` iterations. A frame's result then depends only
  on that frame's handles, as a render farm needs.
- `step(transforms, iterations=1)`: warm-started from the previous result, a
  fixed number of iterations: the interactive preview (one iteration per
  handle move converges over successive moves).
Neither hangs: both are bounded by their iteration count; a non-finite result
raises, and a solve that did not reach `tol` says so in its result (or raises
with `strict=True`).
"""

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


@dataclass
class ArapResult:
    vertices: np.ndarray
    iterations: int
    last_step: float  # largest vertex move of the last iteration, relative to the cage's diagonal
    converged: bool
    seconds: float


class ArapDeformer:
    """ARAP on the cage's tets with handle regions (each moved by an affine) and pinned regions."""

    def __init__(self, rest_vertices: np.ndarray, tets: np.ndarray, handles: list, pins: list | None = None, energy: str = "elements"):
        import igl

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
        self.b = np.concatenate(regs).astype(np.int32)
        energies = {
            "elements": igl.ARAP_ENERGY_TYPE_ELEMENTS,
            "spokes": igl.ARAP_ENERGY_TYPE_SPOKES,
            "spokes_and_rims": igl.ARAP_ENERGY_TYPE_SPOKES_AND_RIMS,
        }
        if energy not in energies:
            raise EngineError(f"unknown ARAP energy {energy!r}; one of {sorted(energies)}")
        self._igl = igl
        self.data = igl.ARAPData()
        self.data.energy = energies[energy]
        self.data.max_iter = 1
        t0 = time.perf_counter()
        igl.arap_precomputation(V, T, 3, self.b, self.data)
        self.precompute_s = time.perf_counter() - t0
        self.U: np.ndarray | None = None  # last result (warm start of `step`)

    def constraints(self, transforms: list) -> np.ndarray:
        """Target positions of the constrained vertices (handles moved by their affines, pins at rest)."""
        if len(transforms) != len(self.handles):
            raise EngineError(f"ARAP has {len(self.handles)} handle regions but got {len(transforms)} transforms")
        parts = [apply_affine(self.rest[h], A) for h, A in zip(self.handles, transforms)]
        parts += [self.rest[p] for p in self.pins]
        return np.ascontiguousarray(np.concatenate(parts) if parts else np.zeros((0, 3)))

    def _iterate(self, bc: np.ndarray, U: np.ndarray, iterations: int, tol: float | None):
        step = np.inf
        it = 0
        for it in range(1, iterations + 1):
            U_new = self._igl.arap_solve(bc, self.data, U)
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
