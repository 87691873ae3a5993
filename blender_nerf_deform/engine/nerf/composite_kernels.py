"""Fused CPU kernels (numba) of volume compositing and of the contraction, for rendering without gradients.

Why: both are a handful of elementwise torch operations over every sample, each
allocating a temporary; one pass per sample here. Measured on 1M samples: the
contraction 7.2x faster (1.8 vs 12.9 ms), the transmittance 1.6x (6.2 vs 9.6 ms);
with the SH kernel about 5 % of a fox frame (the hash encoding and MLPs are the rest). The torch versions (renderer._exclusive_transmittance,
contraction.contract) stay for CUDA, for gradients and as the reference.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import backend

FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}  # NaN and inf keep their meaning

if backend.HAVE_NUMBA:
    from numba import njit, prange

    @njit(cache=True, fastmath=FAST)
    def _exclusive_transmittance(tau, ray_idx, out):
        acc = 0.0
        prev = -1
        for s in range(tau.shape[0]):
            if ray_idx[s] != prev:
                prev = ray_idx[s]
                acc = 0.0
            out[s] = np.exp(-acc)
            acc += tau[s]

    @njit(parallel=True, cache=True, fastmath=FAST)
    def _contract_normalize(p, center, inv_half, out):
        for n in prange(p.shape[0]):
            ux = (p[n, 0] - center[0]) * inv_half[0]
            uy = (p[n, 1] - center[1]) * inv_half[1]
            uz = (p[n, 2] - center[2]) * inv_half[2]
            m = max(abs(ux), abs(uy), abs(uz))
            s = np.float32(1.0)
            if m > 1.0:
                s = (np.float32(2.0) - np.float32(1.0) / m) / m
            out[n, 0] = (ux * s + np.float32(2.0)) * np.float32(0.25)
            out[n, 1] = (uy * s + np.float32(2.0)) * np.float32(0.25)
            out[n, 2] = (uz * s + np.float32(2.0)) * np.float32(0.25)


def exclusive_transmittance(tau: torch.Tensor, ray_idx: torch.Tensor) -> torch.Tensor:
    """exp(-sum of tau over the earlier samples of the same ray), samples sorted by ray (float64 sums)."""
    out = np.empty(tau.shape[0], dtype=np.float32)
    _exclusive_transmittance(tau.detach().contiguous().numpy(), ray_idx.contiguous().numpy(), out)
    return torch.from_numpy(out)


def contract_normalize(points: torch.Tensor, center: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """(contract((p - center) / half) + 2) / 4: an unbounded NeRF's hash-grid coordinates in [0, 1]^3."""
    out = np.empty((points.shape[0], 3), dtype=np.float32)
    _contract_normalize(points.detach().contiguous().numpy(), center.contiguous().numpy(),
                        (1.0 / half).contiguous().numpy(), out)
    return torch.from_numpy(out)
