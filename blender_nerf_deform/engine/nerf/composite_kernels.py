"""Fused CPU kernels (numba) of volume compositing and of the contraction, for rendering without gradients.

Frames (renderer._render_chunk_frame) composite each round of samples with two kernels:
`composite_round` (per sample: weight from the ray's running float64 transmittance, the
samples whose weight earns a colour evaluation, the transmittance carried on) and
`accumulate` (colour, alpha and depth of the selected samples into their rays). They replace
about ten torch operations (and their temporaries) per round.

Why: both are a handful of elementwise torch operations over every sample, each
allocating a temporary; one pass per sample here. The torch versions
(renderer._exclusive_transmittance, contraction.contract) stay for CUDA, for gradients and as the
reference.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import backend

FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}  # NaN and inf keep their meaning

if backend.HAVE_NUMBA:
    from ..kernel_cache import njit, prange

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

    @njit(cache=True, fastmath=FAST)
    def _composite_round(sigma, dt, ray_idx, transmittance, threshold, weights, selected):
        n_sel = 0
        for s in range(sigma.shape[0]):
            r = ray_idx[s]
            tau = np.float64(sigma[s]) * np.float64(dt[s])
            t_ray = transmittance[r]
            decay = np.exp(-tau)
            w = t_ray * (1.0 - decay)
            weights[s] = w
            if w > threshold:
                selected[n_sel] = s
                n_sel += 1
            transmittance[r] = t_ray * decay
        return n_sel

    @njit(cache=True, fastmath=FAST)
    def _accumulate(selected, ray_idx, weights, t, rgb, color, alpha, depth):
        for i in range(selected.shape[0]):
            s = selected[i]
            r = ray_idx[s]
            w = weights[s]
            color[r, 0] += w * rgb[i, 0]
            color[r, 1] += w * rgb[i, 1]
            color[r, 2] += w * rgb[i, 2]
            alpha[r] += w
            depth[r] += w * t[s]


def composite_round(
    sigma: torch.Tensor, dt: torch.Tensor, ray_idx: torch.Tensor, transmittance: torch.Tensor, threshold: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """One round of a frame's samples (sorted by ray, then t, within each ray): (weights (S,) float32, indices
    of the samples whose weight exceeds `threshold`); `transmittance` (float64, per ray) is carried on in place."""
    n = sigma.shape[0]
    weights = np.empty(n, dtype=np.float32)
    selected = np.empty(n, dtype=np.int64)
    k = _composite_round(
        sigma.contiguous().numpy(),
        dt.contiguous().numpy(),
        ray_idx.contiguous().numpy(),
        transmittance.numpy(),
        float(threshold),
        weights,
        selected,
    )
    return torch.from_numpy(weights), torch.from_numpy(selected[:k])


def accumulate(
    selected: torch.Tensor,
    ray_idx: torch.Tensor,
    weights: torch.Tensor,
    t: torch.Tensor,
    rgb: torch.Tensor,
    color: torch.Tensor,
    alpha: torch.Tensor,
    depth: torch.Tensor,
) -> None:
    """color[r] += w rgb, alpha[r] += w, depth[r] += w t for the selected samples (rgb: one row per selected)."""
    _accumulate(
        selected.contiguous().numpy(),
        ray_idx.contiguous().numpy(),
        weights.contiguous().numpy(),
        t.contiguous().numpy(),
        rgb.contiguous().numpy(),
        color.numpy(),
        alpha.numpy(),
        depth.numpy(),
    )


def exclusive_transmittance(tau: torch.Tensor, ray_idx: torch.Tensor) -> torch.Tensor:
    """exp(-sum of tau over the earlier samples of the same ray), samples sorted by ray (float64 sums)."""
    out = np.empty(tau.shape[0], dtype=np.float32)
    _exclusive_transmittance(tau.detach().contiguous().numpy(), ray_idx.contiguous().numpy(), out)
    return torch.from_numpy(out)


def contract_normalize(points: torch.Tensor, center: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """(contract((p - center) / half) + 2) / 4: an unbounded NeRF's hash-grid coordinates in [0, 1]^3."""
    out = np.empty((points.shape[0], 3), dtype=np.float32)
    _contract_normalize(
        points.detach().contiguous().numpy(), center.contiguous().numpy(), (1.0 / half).contiguous().numpy(), out
    )
    return torch.from_numpy(out)
