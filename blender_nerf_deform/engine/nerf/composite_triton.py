"""A frame's render round composited in one Triton kernel (the device path).

Why hand-written: in torch, compositing a round is a score of small kernels (optical depths, the exclusive
transmittance by prefix sums, weights, three index_adds, the carried transmittance); here one program
walks a block of rays, one lane per ray, front to back over the ray's samples of the round: the weight of
each sample from the transmittance carried between rounds, the colour, alpha and depth it adds (samples
below the weight threshold add nothing), and the transmittance the ray carries on. The same float32
weights as the torch formulation, the optical depths summed in float64 as there (sequentially per ray
rather than as differences of one prefix sum: a rounding of float64 apart).

Only imported where `backend.use_triton` says Triton runs (CUDA, or the interpreter).
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl

from ..launch_count import kernel_launch

# Rays per program; the interpreter pays per operation, not per element: far larger blocks there.
BLOCK = 4096 if os.environ.get("TRITON_INTERPRET", "0") == "1" else 64


@triton.jit
def _composite(sigma_ptr, dt_ptr, t_ptr, rgb_ptr, first_ptr, counts_ptr, alive_ptr, trans_ptr, color_ptr,
               alpha_ptr, depth_ptr, n_color_ptr, n_rows, threshold, BLOCK: tl.constexpr):
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = rows < n_rows
    first = tl.load(first_ptr + rows, mask=valid, other=0)
    count = tl.load(counts_ptr + rows, mask=valid, other=0)
    ray = tl.load(alive_ptr + rows, mask=valid, other=0)
    carried = tl.load(trans_ptr + ray, mask=valid, other=1.0)  # float64
    carried32 = carried.to(tl.float32)
    depth_sum = tl.zeros((BLOCK,), dtype=tl.float64)
    r = tl.zeros((BLOCK,), dtype=tl.float32)
    g = tl.zeros((BLOCK,), dtype=tl.float32)
    b = tl.zeros((BLOCK,), dtype=tl.float32)
    a = tl.zeros((BLOCK,), dtype=tl.float32)
    z = tl.zeros((BLOCK,), dtype=tl.float32)
    lit_count = tl.zeros((BLOCK,), dtype=tl.int64)
    longest = tl.max(tl.where(valid, count, 0), axis=0)
    i = 0
    while i < longest:
        on = valid & (i < count)
        s = first + i
        tau = tl.load(sigma_ptr + s, mask=on, other=0.0) * tl.load(dt_ptr + s, mask=on, other=0.0)
        trans = tl.exp(-depth_sum).to(tl.float32) * carried32
        w = trans * (1.0 - tl.exp(-tau))
        lit = on & (w > threshold)
        w = tl.where(lit, w, 0.0)
        r += w * tl.load(rgb_ptr + s * 3, mask=lit, other=0.0)
        g += w * tl.load(rgb_ptr + s * 3 + 1, mask=lit, other=0.0)
        b += w * tl.load(rgb_ptr + s * 3 + 2, mask=lit, other=0.0)
        a += w
        z += w * tl.load(t_ptr + s, mask=lit, other=0.0)
        lit_count += lit.to(tl.int64)
        depth_sum += tau.to(tl.float64)
        i += 1
    # Each ray appears once in a round: plain adds into its pixel.
    tl.store(color_ptr + ray * 3, tl.load(color_ptr + ray * 3, mask=valid, other=0.0) + r, mask=valid)
    tl.store(color_ptr + ray * 3 + 1, tl.load(color_ptr + ray * 3 + 1, mask=valid, other=0.0) + g, mask=valid)
    tl.store(color_ptr + ray * 3 + 2, tl.load(color_ptr + ray * 3 + 2, mask=valid, other=0.0) + b, mask=valid)
    tl.store(alpha_ptr + ray, tl.load(alpha_ptr + ray, mask=valid, other=0.0) + a, mask=valid)
    tl.store(depth_ptr + ray, tl.load(depth_ptr + ray, mask=valid, other=0.0) + z, mask=valid)
    tl.store(trans_ptr + ray, carried * tl.exp(-depth_sum), mask=valid)
    tl.atomic_add(n_color_ptr, tl.sum(lit_count, axis=0))


def composite_round(sigma, dt, t, rgb, first, counts, alive, transmittance, color, alpha, depth,
                    threshold: float) -> torch.Tensor:
    """Adds a round's samples (flat, sorted by row then t; row i's from first[i], counts[i] of them, ray
    alive[i]) into color (N, 3), alpha and depth (N,) and carries `transmittance` (N,) float64 on, in place;
    returns the number of samples above the weight threshold (a 0-dim tensor on the device)."""
    n_rows = first.shape[0]
    n_color = torch.zeros((), dtype=torch.int64, device=sigma.device)
    if n_rows:
        with kernel_launch("composite"):
            _composite[(triton.cdiv(n_rows, BLOCK),)](
                sigma.contiguous(), dt.contiguous(), t.contiguous(), rgb.contiguous(), first.contiguous(),
                counts.contiguous(), alive.contiguous(), transmittance, color, alpha, depth, n_color, n_rows,
                float(threshold), BLOCK=BLOCK)
    return n_color
