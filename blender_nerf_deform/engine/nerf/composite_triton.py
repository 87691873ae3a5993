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
def _composite(
    sigma_ptr,
    dt_ptr,
    t_ptr,
    rgb_ptr,
    first_ptr,
    counts_ptr,
    alive_ptr,
    trans_ptr,
    color_ptr,
    alpha_ptr,
    depth_ptr,
    n_color_ptr,
    n_rows,
    threshold,
    BLOCK: tl.constexpr,
):
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


def composite_round(
    sigma, dt, t, rgb, first, counts, alive, transmittance, color, alpha, depth, threshold: float
) -> torch.Tensor:
    """Adds a round's samples (flat, sorted by row then t; row i's from first[i], counts[i] of them, ray
    alive[i]) into color (N, 3), alpha and depth (N,) and carries `transmittance` (N,) float64 on, in place;
    returns the number of samples above the weight threshold (a 0-dim tensor on the device)."""
    n_rows = first.shape[0]
    n_color = torch.zeros((), dtype=torch.int64, device=sigma.device)
    if n_rows:
        with kernel_launch("composite"):
            _composite[(triton.cdiv(n_rows, BLOCK),)](
                sigma.contiguous(),
                dt.contiguous(),
                t.contiguous(),
                rgb.contiguous(),
                first.contiguous(),
                counts.contiguous(),
                alive.contiguous(),
                transmittance,
                color,
                alpha,
                depth,
                n_color,
                n_rows,
                float(threshold),
                BLOCK=BLOCK,
            )
    return n_color


# Training: the batch's one round, composited with gradients (forward and backward, one kernel each).


@triton.jit
def _row_span(first_ptr, counts_ptr, alive_ptr, n_rows, size, BLOCK: tl.constexpr):
    """This program's rows: which are real, where each row's samples start, how many (cut at `size`), its ray."""
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = rows < n_rows
    first = tl.load(first_ptr + rows, mask=valid, other=0)
    count = tl.minimum(tl.load(counts_ptr + rows, mask=valid, other=0), tl.maximum(size - first, 0))
    return valid, first, count, tl.load(alive_ptr + rows, mask=valid, other=0)


@triton.jit
def _train_forward(
    sigma_ptr,
    dt_ptr,
    t_ptr,
    rgb_ptr,
    first_ptr,
    counts_ptr,
    alive_ptr,
    w_ptr,
    color_ptr,
    alpha_ptr,
    depth_ptr,
    n_rows,
    size,
    BLOCK: tl.constexpr,
):
    valid, first, count, ray = _row_span(first_ptr, counts_ptr, alive_ptr, n_rows, size, BLOCK)
    acc = tl.zeros((BLOCK,), dtype=tl.float64)
    r = tl.zeros((BLOCK,), dtype=tl.float32)
    g = tl.zeros((BLOCK,), dtype=tl.float32)
    b = tl.zeros((BLOCK,), dtype=tl.float32)
    a = tl.zeros((BLOCK,), dtype=tl.float32)
    z = tl.zeros((BLOCK,), dtype=tl.float32)
    longest = tl.max(tl.where(valid, count, 0), axis=0)
    i = 0
    while i < longest:
        on = valid & (i < count)
        s = first + i
        tau = tl.load(sigma_ptr + s, mask=on, other=0.0) * tl.load(dt_ptr + s, mask=on, other=0.0)
        w = tl.exp(-acc).to(tl.float32) * (1.0 - tl.exp(-tau))
        tl.store(w_ptr + s, w, mask=on)
        r += w * tl.load(rgb_ptr + s * 3, mask=on, other=0.0)
        g += w * tl.load(rgb_ptr + s * 3 + 1, mask=on, other=0.0)
        b += w * tl.load(rgb_ptr + s * 3 + 2, mask=on, other=0.0)
        a += w
        z += w * tl.load(t_ptr + s, mask=on, other=0.0)
        acc += tau.to(tl.float64)
        i += 1
    tl.store(color_ptr + ray * 3, r, mask=valid)
    tl.store(color_ptr + ray * 3 + 1, g, mask=valid)
    tl.store(color_ptr + ray * 3 + 2, b, mask=valid)
    tl.store(alpha_ptr + ray, a, mask=valid)
    tl.store(depth_ptr + ray, z, mask=valid)


@triton.jit
def _sensitivity(s, on, ray, w_ptr, rgb_ptr, t_ptr, gw_ptr, gc_ptr, ga_ptr, gd_ptr):
    """e = dL/dw of a sample: its own weight's gradient plus what it adds to its ray's pixel, alpha, depth."""
    e = tl.load(gw_ptr + s, mask=on, other=0.0)
    e += tl.load(gc_ptr + ray * 3, mask=on, other=0.0) * tl.load(rgb_ptr + s * 3, mask=on, other=0.0)
    e += tl.load(gc_ptr + ray * 3 + 1, mask=on, other=0.0) * tl.load(rgb_ptr + s * 3 + 1, mask=on, other=0.0)
    e += tl.load(gc_ptr + ray * 3 + 2, mask=on, other=0.0) * tl.load(rgb_ptr + s * 3 + 2, mask=on, other=0.0)
    e += tl.load(ga_ptr + ray, mask=on, other=0.0)
    e += tl.load(gd_ptr + ray, mask=on, other=0.0) * tl.load(t_ptr + s, mask=on, other=0.0)
    return e


@triton.jit
def _train_backward(
    sigma_ptr,
    dt_ptr,
    t_ptr,
    rgb_ptr,
    first_ptr,
    counts_ptr,
    alive_ptr,
    w_ptr,
    gw_ptr,
    gc_ptr,
    ga_ptr,
    gd_ptr,
    gsigma_ptr,
    grgb_ptr,
    n_rows,
    size,
    BLOCK: tl.constexpr,
):
    """dL/dtau_k = e_k T_(k+1) - sum over the later samples i of e_i w_i (T_(k+1): the transmittance past k)."""
    valid, first, count, ray = _row_span(first_ptr, counts_ptr, alive_ptr, n_rows, size, BLOCK)
    longest = tl.max(tl.where(valid, count, 0), axis=0)
    total = tl.zeros((BLOCK,), dtype=tl.float32)
    i = 0
    while i < longest:
        on = valid & (i < count)
        s = first + i
        total += _sensitivity(s, on, ray, w_ptr, rgb_ptr, t_ptr, gw_ptr, gc_ptr, ga_ptr, gd_ptr) * tl.load(
            w_ptr + s, mask=on, other=0.0
        )
        i += 1
    acc = tl.zeros((BLOCK,), dtype=tl.float64)
    done = tl.zeros((BLOCK,), dtype=tl.float32)
    i = 0
    while i < longest:
        on = valid & (i < count)
        s = first + i
        e = _sensitivity(s, on, ray, w_ptr, rgb_ptr, t_ptr, gw_ptr, gc_ptr, ga_ptr, gd_ptr)
        w = tl.load(w_ptr + s, mask=on, other=0.0)
        dt = tl.load(dt_ptr + s, mask=on, other=0.0)
        acc += (tl.load(sigma_ptr + s, mask=on, other=0.0) * dt).to(tl.float64)
        done += e * w
        g_tau = e * tl.exp(-acc).to(tl.float32) - (total - done)
        tl.store(gsigma_ptr + s, g_tau * dt, mask=on)
        tl.store(grgb_ptr + s * 3, w * tl.load(gc_ptr + ray * 3, mask=on, other=0.0), mask=on)
        tl.store(grgb_ptr + s * 3 + 1, w * tl.load(gc_ptr + ray * 3 + 1, mask=on, other=0.0), mask=on)
        tl.store(grgb_ptr + s * 3 + 2, w * tl.load(gc_ptr + ray * 3 + 2, mask=on, other=0.0), mask=on)
        i += 1


class CompositeTrain(torch.autograd.Function):
    """(color (N, 3), alpha (N,), depth (N,), w (S,)) of a training round's samples: flat, sorted by row then
    t, row i's from first[i] (counts[i] of them, cut at `size`), ray alive[i], each ray in one row; samples
    in no row weigh 0. Differentiable in sigma (S,) and rgb (S, 3)."""

    @staticmethod
    def forward(ctx, sigma, rgb, dt, t, first, counts, alive, n_rays):
        sigma, rgb, dt, t = sigma.contiguous(), rgb.contiguous(), dt.contiguous(), t.contiguous()
        size, n_rows, dev = sigma.shape[0], first.shape[0], sigma.device
        w = torch.zeros(size, dtype=torch.float32, device=dev)
        color = torch.zeros((n_rays, 3), dtype=torch.float32, device=dev)
        alpha = torch.zeros(n_rays, dtype=torch.float32, device=dev)
        depth = torch.zeros(n_rays, dtype=torch.float32, device=dev)
        if n_rows and size:
            with kernel_launch("composite_train"):
                _train_forward[(triton.cdiv(n_rows, BLOCK),)](
                    sigma, dt, t, rgb, first, counts, alive, w, color, alpha, depth, n_rows, size, BLOCK=BLOCK
                )
        ctx.save_for_backward(sigma, rgb, dt, t, first, counts, alive, w)
        ctx.n_rays = n_rays
        return color, alpha, depth, w

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, g_w):
        sigma, rgb, dt, t, first, counts, alive, w = ctx.saved_tensors
        n_rays, dev = ctx.n_rays, sigma.device

        def given(g, shape):  # an output the loss did not use has no gradient
            return torch.zeros(shape, dtype=torch.float32, device=dev) if g is None else g.contiguous()

        g_color, g_alpha = given(g_color, (n_rays, 3)), given(g_alpha, (n_rays,))
        g_depth, g_w = given(g_depth, (n_rays,)), given(g_w, w.shape)
        g_sigma, g_rgb = torch.zeros_like(sigma), torch.zeros_like(rgb)
        n_rows, size = first.shape[0], sigma.shape[0]
        if n_rows and size:
            with kernel_launch("composite_train_backward"):
                _train_backward[(triton.cdiv(n_rows, BLOCK),)](
                    sigma,
                    dt,
                    t,
                    rgb,
                    first,
                    counts,
                    alive,
                    w,
                    g_w,
                    g_color,
                    g_alpha,
                    g_depth,
                    g_sigma,
                    g_rgb,
                    n_rows,
                    size,
                    BLOCK=BLOCK,
                )
        return g_sigma, g_rgb, None, None, None, None, None, None
