"""A render round's march in one Triton kernel (the device path): `march_kernels.march_round_device`.

Why hand-written: the torch formulation marches blocks of lattice steps for all rays at once, a score of
small kernels per block and per background step, so a round costs hundreds of launches whatever its size;
here one program walks a block of rays, one lane per ray, each taking its own steps (lattice steps in the box,
background steps) until it has k samples, ends, or the round's blocks of steps are spent; the
program leaves each loop as soon as none of its lanes is in it. Every sample is the one the torch formulation and the numba
kernels place (the same float32 operations in the same order; on CUDA the compiler may fuse a multiply and
an add, which moves a sample on a cell boundary by one rounding at most).

Only imported where `backend.use_triton` says Triton runs (CUDA, or the interpreter), so that `triton.jit`
sees the interpreter switch when it decorates the kernel.
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl

from ..launch_count import kernel_launch

# Rays per program; the interpreter pays per operation, not per element: far larger blocks there.
BLOCK = 4096 if os.environ.get("TRITON_INTERPRET", "0") == "1" else 64

# march_kernels' phases, as constants the kernel can read.
PHASE_BEFORE, PHASE_INNER, PHASE_AFTER, PHASE_DONE = (tl.constexpr(v) for v in range(4))


@triton.jit
def _inner_occupied(px, py, pz, lo_ptr, scale_ptr, mask_ptr, res):
    fx = tl.floor((px - tl.load(lo_ptr)) * tl.load(scale_ptr))
    fy = tl.floor((py - tl.load(lo_ptr + 1)) * tl.load(scale_ptr + 1))
    fz = tl.floor((pz - tl.load(lo_ptr + 2)) * tl.load(scale_ptr + 2))
    inside = (fx >= 0) & (fx < res) & (fy >= 0) & (fy < res) & (fz >= 0) & (fz < res)
    cell = (tl.where(inside, fx, 0.0).to(tl.int64) + res * tl.where(inside, fy, 0.0).to(tl.int64)
            + res * res * tl.where(inside, fz, 0.0).to(tl.int64))
    return inside & (tl.load(mask_ptr + cell, mask=inside, other=0) != 0)


@triton.jit
def _units(px, py, pz, center_ptr, inv_half_ptr):
    ux = (px - tl.load(center_ptr)) * tl.load(inv_half_ptr)
    uy = (py - tl.load(center_ptr + 1)) * tl.load(inv_half_ptr + 1)
    uz = (pz - tl.load(center_ptr + 2)) * tl.load(inv_half_ptr + 2)
    m = tl.maximum(tl.maximum(tl.abs(ux), tl.abs(uy)), tl.abs(uz))
    return ux, uy, uz, m


@triton.jit
def _bg_occupied(px, py, pz, center_ptr, inv_half_ptr, bg_mask_ptr, bg_res, bg_quarter):
    ux, uy, uz, m = _units(px, py, pz, center_ptr, inv_half_ptr)
    mm = tl.maximum(m, 1.0)  # (no division by 0 where m is not used)
    s = tl.where(m > 1.0, (2.0 - 1.0 / mm) / mm, 1.0)
    fx = tl.floor((ux * s + 2.0) * bg_quarter)
    fy = tl.floor((uy * s + 2.0) * bg_quarter)
    fz = tl.floor((uz * s + 2.0) * bg_quarter)
    inside = (fx >= 0) & (fx < bg_res) & (fy >= 0) & (fy < bg_res) & (fz >= 0) & (fz < bg_res)
    cell = (tl.where(inside, fx, 0.0).to(tl.int64) + bg_res * tl.where(inside, fy, 0.0).to(tl.int64)
            + bg_res * bg_res * tl.where(inside, fz, 0.0).to(tl.int64))
    return inside & (tl.load(bg_mask_ptr + cell, mask=inside, other=0) != 0)


@triton.jit
def _march(o_ptr, d_ptr, alive_ptr, active_ptr, phase_ptr, j_ptr, t_ptr, j_end_ptr, u_ptr, t_in_ptr, t_out_ptr,
           t_far_ptr, ts_ptr, dts_ptr, counts_ptr, lo_ptr, scale_ptr, mask_ptr, center_ptr, inv_half_ptr,
           bg_mask_ptr, n, k, n_blocks, block_steps, bg_per_block, res, step, bg_res, bg_quarter, bg_step,
           HAS_BG: tl.constexpr, BLOCK: tl.constexpr):
    lanes = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = lanes < n
    ray = tl.load(alive_ptr + lanes, mask=valid, other=0)
    busy = valid & (tl.load(active_ptr + lanes, mask=valid, other=0) != 0)
    ox = tl.load(o_ptr + ray * 3, mask=valid, other=0.0)
    oy = tl.load(o_ptr + ray * 3 + 1, mask=valid, other=0.0)
    oz = tl.load(o_ptr + ray * 3 + 2, mask=valid, other=0.0)
    dx = tl.load(d_ptr + ray * 3, mask=valid, other=0.0)
    dy = tl.load(d_ptr + ray * 3 + 1, mask=valid, other=0.0)
    dz = tl.load(d_ptr + ray * 3 + 2, mask=valid, other=0.0)
    ph = tl.load(phase_ptr + ray, mask=valid, other=PHASE_DONE).to(tl.int32)
    j = tl.load(j_ptr + ray, mask=valid, other=0)
    t_bg = tl.load(t_ptr + ray, mask=valid, other=0.0)
    j_end = tl.load(j_end_ptr + ray, mask=valid, other=0)
    u = tl.load(u_ptr + ray, mask=valid, other=0.0)
    t_in = tl.load(t_in_ptr + ray, mask=valid, other=0.0)
    t_out = tl.load(t_out_ptr + ray, mask=valid, other=0.0)
    t_far = tl.load(t_far_ptr + ray, mask=valid, other=0.0)
    count = tl.zeros((BLOCK,), dtype=tl.int64)
    # As the torch formulation walks: blocks of up to `block_steps` lattice steps in the box, each followed
    # by up to `bg_per_block` background steps; a program leaves a loop once none of its rays is in it.
    b = 0
    going = busy & (ph < PHASE_DONE)
    while (b < n_blocks) & (tl.max(going.to(tl.int32), axis=0) > 0):
        inner = going & (ph == PHASE_INNER)
        lattice = inner & (j < j_end) & (count < k)
        i = 0
        while (i < block_steps) & (tl.max(lattice.to(tl.int32), axis=0) > 0):
            t = (j.to(tl.float32) + u) * step
            hit = lattice & _inner_occupied(ox + dx * t, oy + dy * t, oz + dz * t, lo_ptr, scale_ptr, mask_ptr, res)
            tl.store(ts_ptr + lanes * k + count, t, mask=hit)
            tl.store(dts_ptr + lanes * k + count, tl.zeros_like(t) + step, mask=hit)
            count += hit.to(tl.int64)
            j = tl.where(lattice, j + 1, j)
            lattice = lattice & (j < j_end) & (count < k)
            i += 1
        # A ray whose box segment ended (and that is not full) turns to the background, or is done.
        ends = inner & (j >= j_end) & (count < k)
        if HAS_BG:
            t_bg = tl.where(ends, t_out, t_bg)
            ph = tl.where(ends, PHASE_AFTER, ph)
            bg = going & ((ph == PHASE_BEFORE) | (ph == PHASE_AFTER)) & (count < k)
            i = 0
            while (i < bg_per_block) & (tl.max(bg.to(tl.int32), axis=0) > 0):
                before = ph == PHASE_BEFORE
                end = tl.where(before, t_in, t_far)
                over = bg & ~(t_bg < end)
                ph = tl.where(over, tl.where(before, PHASE_INNER, PHASE_DONE), ph)
                go = bg & ~over
                _, _, _, m = _units(ox + dx * t_bg, oy + dy * t_bg, oz + dz * t_bg, center_ptr, inv_half_ptr)
                dt = bg_step * tl.where(m > 1.0, m, 1.0)
                t_next = t_bg + dt
                t_next = tl.where(t_next < end, t_next, end)
                tsam = t_bg + u * (t_next - t_bg)
                hit = go & _bg_occupied(ox + dx * tsam, oy + dy * tsam, oz + dz * tsam, center_ptr, inv_half_ptr,
                                        bg_mask_ptr, bg_res, bg_quarter)
                tl.store(ts_ptr + lanes * k + count, tsam, mask=hit)
                tl.store(dts_ptr + lanes * k + count, t_next - t_bg, mask=hit)
                count += hit.to(tl.int64)
                t_bg = tl.where(go, t_next, t_bg)
                bg = going & ((ph == PHASE_BEFORE) | (ph == PHASE_AFTER)) & (count < k)
                i += 1
        else:
            ph = tl.where(ends, PHASE_DONE, ph)
        going = going & (ph < PHASE_DONE) & (count < k)
        b += 1
    tl.store(phase_ptr + ray, ph.to(tl.int8), mask=busy)
    tl.store(j_ptr + ray, j, mask=busy)
    tl.store(t_ptr + ray, t_bg, mask=busy)
    tl.store(counts_ptr + lanes, count, mask=valid)


def march_round(o, d, alive, active, s, k: int, g, n_blocks: int, block_steps: int, bg_per_block: int):
    """Up to k next samples of each ray in `alive` whose `active` is True, in `n_blocks` blocks of up to
    `block_steps` lattice steps and `bg_per_block` background steps: (t (A, k), dt (A, k), counts (A,)),
    slots past a ray's count 0; `s` (march_kernels.MarchState) advances."""
    n = alive.shape[0]
    dev = o.device
    ts = torch.zeros((n, k), dtype=torch.float32, device=dev)
    dts = torch.zeros((n, k), dtype=torch.float32, device=dev)
    counts = torch.empty(n, dtype=torch.int64, device=dev)
    if n == 0:
        return ts, dts, counts
    mask = g.mask.view(torch.uint8)
    if g.has_bg:
        center, inv_half, bg_mask = g.center, g.inv_half, g.bg_mask.view(torch.uint8)
        bg_res, bg_quarter, bg_step = g.bg_res, g.bg_res / 4.0, g.bg_step
    else:  # unused by the kernel
        center, inv_half, bg_mask, bg_res, bg_quarter, bg_step = g.lo, g.scale, mask, 1, 0.25, 1.0
    with kernel_launch("march"):
        _march[(triton.cdiv(n, BLOCK),)](
            o.contiguous(), d.contiguous(), alive.contiguous(), active.contiguous().view(torch.uint8), s.phase,
            s.j, s.t, s.j_end, s.u, s.t_in, s.t_out, s.t_far, ts, dts, counts, g.lo, g.scale, mask, center,
            inv_half, bg_mask, n, k, n_blocks, block_steps, bg_per_block, g.res, float(g.step), bg_res, float(bg_quarter), float(bg_step),
            HAS_BG=bool(g.has_bg), BLOCK=BLOCK)
    return ts, dts, counts
