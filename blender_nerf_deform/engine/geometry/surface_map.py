"""The deformed surface as one sparse matrix product: what the worker answers the live preview with.

`Embedding.apply` (pure numpy, the add-on's own path) gathers 4 cage vertices per
surface vertex, slow on a dense demo mesh. The same map as a CSR matrix (surface
vertices x cage vertices, 4 weights a row), built once per embedding, applies
several times faster, which is what lets a preview update fit in the solve's own
time.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

from .embedding import Embedding


class SurfaceMap:
    def __init__(self, embedding: Embedding, n_cage_vertices: int):
        n = len(embedding.corners)
        self.matrix = scipy.sparse.csr_matrix(
            (
                np.asarray(embedding.weights, dtype=np.float64).ravel(),
                np.asarray(embedding.corners).ravel(),
                np.arange(0, 4 * n + 1, 4),
            ),
            shape=(n, n_cage_vertices),
        )

    def apply(self, deformed_vertices: np.ndarray) -> np.ndarray:
        """(N, 3) surface positions for the given (n_cage_vertices, 3) cage positions."""
        return self.matrix @ np.asarray(deformed_vertices, dtype=np.float64)
