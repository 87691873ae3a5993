"""Barycentric maps of a tetrahedral cage, vectorised over all tets (pure numpy).

The barycentric matrix of a tet with vertices a, b, c, d is (docs/ARCHITECTURE.md, Conventions)

    T = | a b c d |      λ = T⁻¹ [p; 1],   p = T λ (first three rows)
        | 1 1 1 1 |

so the deformed→rest map of one tet is the 4x4 affine `T_rest · T_deformed⁻¹`.
A point on a face shared by two tets gets the same rest position from either
tet: on that face the barycentric coordinate of the opposite vertex is zero and
the other three are those of the shared triangle, whose vertices both tets map
identically.

Pure numpy on purpose: the Blender add-on (no torch) uses it through the
surface embedding. The torch point location of `locate.py` uses the
same formulas on tensors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import EngineError


def as_tets(vertices: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.asarray(vertices, dtype=np.float64)
    tets = np.asarray(tets)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise EngineError(f"cage vertices must have shape (N, 3), got {vertices.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4 or not np.issubdtype(tets.dtype, np.integer):
        raise EngineError(f"cage tets must be an (M, 4) integer array, got {tets.shape} {tets.dtype}")
    if tets.size and (tets.min() < 0 or tets.max() >= len(vertices)):
        raise EngineError(f"cage tets index vertices outside 0..{len(vertices) - 1}")
    return vertices, tets.astype(np.int64, copy=False)


def tet_matrices(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M, 4, 4) barycentric matrices T: columns are the tet's vertices, last row ones."""
    vertices, tets = as_tets(vertices, tets)
    T = np.ones((len(tets), 4, 4))
    T[:, :3, :] = vertices[tets].transpose(0, 2, 1)
    return T


def tet_inverses(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M, 4, 4) T⁻¹, in closed form from the edge matrix (no general 4x4 inverse).

    With D = [b-a, c-a, d-a], λ_bcd = D⁻¹ (p - a) and λ_a = 1 - Σλ_bcd, so
    T⁻¹ = [[-1ᵀ D⁻¹, 1 + 1ᵀ D⁻¹ a], [D⁻¹, -D⁻¹ a]]. Degenerate tets get NaN rows.
    """
    vertices, tets = as_tets(vertices, tets)
    P = vertices[tets]  # (M, 4, 3)
    a = P[:, 0]
    D = (P[:, 1:] - a[:, None, :]).transpose(0, 2, 1)  # (M, 3, 3) columns b-a, c-a, d-a
    det = np.linalg.det(D)
    Dinv = np.full_like(D, np.nan)
    ok = np.abs(det) > 0
    Dinv[ok] = np.linalg.inv(D[ok])
    inv = np.empty((len(tets), 4, 4))
    inv[:, 1:, :3] = Dinv
    inv[:, 1:, 3] = -np.einsum("mij,mj->mi", Dinv, a)
    inv[:, 0, :3] = -Dinv.sum(axis=1)
    inv[:, 0, 3] = 1.0 - inv[:, 1:, 3].sum(axis=1)
    return inv


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M,) signed volume of each tet: det[b-a, c-a, d-a] / 6 (positive = consistently oriented)."""
    vertices, tets = as_tets(vertices, tets)
    P = vertices[tets]
    e = P[:, 1:] - P[:, :1]
    return np.einsum("mi,mi->m", e[:, 0], np.cross(e[:, 1], e[:, 2])) / 6.0


def deformed_to_rest_affines(rest_vertices: np.ndarray, deformed_vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M, 4, 4) affine of each tet mapping deformed space to rest space: T_rest · T_deformed⁻¹."""
    rest_vertices, tets = as_tets(rest_vertices, tets)
    deformed_vertices = np.asarray(deformed_vertices, dtype=np.float64)
    if deformed_vertices.shape != rest_vertices.shape:
        raise EngineError(
            f"deformed cage vertices have shape {deformed_vertices.shape}, the rest cage has {rest_vertices.shape}"
        )
    return tet_matrices(rest_vertices, tets) @ tet_inverses(deformed_vertices, tets)


@dataclass(frozen=True)
class InversionReport:
    """Tets a deformation turned inside out (det F < 0) or flattened (|det F| tiny)."""

    det: np.ndarray  # (M,) determinant of each tet's deformation gradient F = D_def · D_rest⁻¹
    inverted: np.ndarray  # indices with det F < -tol
    degenerate: np.ndarray  # indices with |det F| <= tol

    @property
    def n_inverted(self) -> int:
        return int(len(self.inverted))

    @property
    def n_degenerate(self) -> int:
        return int(len(self.degenerate))

    @property
    def ok(self) -> bool:
        return self.n_inverted == 0 and self.n_degenerate == 0

    def summary(self) -> str:
        return (
            f"{self.n_inverted} inverted and {self.n_degenerate} degenerate of {len(self.det)} tets "
            f"(min det F {self.det.min():.3g})"
        )


def inversion_report(
    rest_vertices: np.ndarray, deformed_vertices: np.ndarray, tets: np.ndarray, tol: float = 1e-6
) -> InversionReport:
    """Determinant of the deformation gradient of every tet: the volume ratio deformed/rest, signed.

    Inverted tets (det F < -tol) break the barycentric map (a deformed point can
    lie in two deformed tets); degenerate ones (|det F| <= tol) have no inverse.
    """
    rest_vertices, tets = as_tets(rest_vertices, tets)
    return inversion_from_det(signed_volumes(deformed_vertices, tets) / signed_volumes(rest_vertices, tets), tol)


def inversion_from_det(det: np.ndarray, tol: float = 1e-6) -> InversionReport:
    """The InversionReport of per-tet det F values (volume ratios deformed / rest, signed)."""
    det = np.nan_to_num(np.asarray(det, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return InversionReport(det=det, inverted=np.flatnonzero(det < -tol), degenerate=np.flatnonzero(np.abs(det) <= tol))


def boundary_faces(tets: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """(F, 3) faces used by exactly one tet, wound outward: for positively oriented tets as
    given, or, with `vertices`, away from each face's own tet whatever its orientation."""
    tets = np.asarray(tets, dtype=np.int64)
    # The face opposite each vertex, ordered so its normal points out of a positive tet.
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    faces = faces[once]
    if vertices is not None:
        opposite = np.concatenate([tets[:, 0], tets[:, 1], tets[:, 2], tets[:, 3]])[once]
        v = np.asarray(vertices, dtype=np.float64)
        a, b, c = (v[faces[:, k]] for k in range(3))
        inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), v[opposite] - a) > 0
        faces[inward] = faces[inward][:, [0, 2, 1]]
    return faces
