"""Lazy (sparse) Adam on CPU (numba): updates only the hash-table rows that received a gradient.

Why: a hash table has millions of rows and a training step touches a few
percent of them; torch's dense Adam would rewrite them all.
As instant-ngp does, rows without gradient keep their moments unchanged.
Used by the trainer when `backend.use_kernels` says so.
"""

from __future__ import annotations

import numpy as np

from .. import backend

if backend.HAVE_NUMBA:
    from ..kernel_cache import njit, prange

    @njit(parallel=True, cache=True, fastmath=True)
    def sparse_adam(param, grad, m, v, touched, lr, b1, b2, eps, bc1, bc2):
        """Adam on the rows marked in `touched` (others keep their state: a lazy Adam, as instant-ngp)."""
        nf = param.shape[1]
        for r in prange(param.shape[0]):
            if touched[r] == 0:
                continue
            touched[r] = 0
            for f in range(nf):
                g = grad[r, f]
                grad[r, f] = 0.0
                mm = b1 * m[r, f] + (1.0 - b1) * g
                vv = b2 * v[r, f] + (1.0 - b2) * g * g
                m[r, f] = mm
                v[r, f] = vv
                param[r, f] -= lr * (mm / bc1) / (np.sqrt(vv / bc2) + eps)
