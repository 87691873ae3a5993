"""A render round's march in one Triton kernel (the device path): `march_kernels.march_round_device`.

Why hand-written: the torch formulation marches blocks of lattice steps for all rays at once, a score of
small kernels per block and per background step, so a round costs hundreds of launches whatever its size;
here one program walks a block of rays, one lane per ray, each taking its own steps (lattice steps in the box,
background steps) until it has k samples, ends, or the round's blocks of steps are spent; the
program leaves each loop as soon as none of its lanes is in it. Every sample is the one the torch
formulation and the numba kernels place (the same float32 operations in the same order; on CUDA the
compiler may fuse a multiply and an add, which moves a sample on a cell boundary by one rounding at most).

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
    cell = (
        tl.where(inside, fx, 0.0).to(tl.int64)
        + res * tl.where(inside, fy, 0.0).to(tl.int64)
        + res * res * tl.where(inside, fz, 0.0).to(tl.int64)
    )
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
    cell = (
        tl.where(inside, fx, 0.0).to(tl.int64)
        + bg_res * tl.where(inside, fy, 0.0).to(tl.int64)
        + bg_res * bg_res * tl.where(inside, fz, 0.0).to(tl.int64)
    )
    return inside & (tl.load(bg_mask_ptr + cell, mask=inside, other=0) != 0)


@triton.jit
def _march(
    o_ptr,
    d_ptr,
    alive_ptr,
    active_ptr,
    phase_ptr,
    j_ptr,
    t_ptr,
    j_end_ptr,
    u_ptr,
    t_in_ptr,
    t_out_ptr,
    t_far_ptr,
    ts_ptr,
    dts_ptr,
    counts_ptr,
    lo_ptr,
    scale_ptr,
    mask_ptr,
    center_ptr,
    inv_half_ptr,
    bg_mask_ptr,
    n,
    k,
    n_blocks,
    block_steps,
    bg_per_block,
    res,
    step,
    bg_res,
    bg_quarter,
    bg_step,
    HAS_BG: tl.constexpr,
    BLOCK: tl.constexpr,
):
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
                hit = go & _bg_occupied(
                    ox + dx * tsam,
                    oy + dy * tsam,
                    oz + dz * tsam,
                    center_ptr,
                    inv_half_ptr,
                    bg_mask_ptr,
                    bg_res,
                    bg_quarter,
                )
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


@triton.jit
def _ray_box(ox, oy, oz, ix, iy, iz, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z):
    """renderer.ray_box: entry and exit distances through the box (exit <= entry: a miss)."""
    ax = (lo_x - ox) * ix
    bx = (hi_x - ox) * ix
    ay = (lo_y - oy) * iy
    by = (hi_y - oy) * iy
    az = (lo_z - oz) * iz
    bz = (hi_z - oz) * iz
    near = tl.maximum(tl.maximum(tl.minimum(ax, bx), tl.minimum(ay, by)), tl.minimum(az, bz))
    far = tl.minimum(tl.minimum(tl.maximum(ax, bx), tl.maximum(ay, by)), tl.maximum(az, bz))
    return near, far


@triton.jit
def _inverse(v):
    return 1.0 / tl.where(tl.abs(v) < 1e-12, 1e-12, v)


@triton.jit
def _setup(
    o_ptr,
    d_ptr,
    u_ptr,
    box_ptr,
    center_ptr,
    inv_half_ptr,
    phase_ptr,
    j_ptr,
    j_end_ptr,
    t_ptr,
    t_in_ptr,
    t_out_ptr,
    t_far_ptr,
    n,
    near,
    step,
    max_steps,
    far_radius,
    HAS_BG: tl.constexpr,
    BLOCK: tl.constexpr,
):
    rays = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = rays < n
    ox = tl.load(o_ptr + rays * 3, mask=valid, other=0.0)
    oy = tl.load(o_ptr + rays * 3 + 1, mask=valid, other=0.0)
    oz = tl.load(o_ptr + rays * 3 + 2, mask=valid, other=0.0)
    ix = _inverse(tl.load(d_ptr + rays * 3, mask=valid, other=1.0))
    iy = _inverse(tl.load(d_ptr + rays * 3 + 1, mask=valid, other=1.0))
    iz = _inverse(tl.load(d_ptr + rays * 3 + 2, mask=valid, other=1.0))
    u = tl.load(u_ptr + rays, mask=valid, other=0.5)
    t_in, t_out = _ray_box(
        ox,
        oy,
        oz,
        ix,
        iy,
        iz,
        tl.load(box_ptr),
        tl.load(box_ptr + 1),
        tl.load(box_ptr + 2),
        tl.load(box_ptr + 3),
        tl.load(box_ptr + 4),
        tl.load(box_ptr + 5),
    )
    t_in = tl.maximum(t_in, near)
    hit = t_out > t_in
    # Lattice indices of the first sample at or after the entry and one past the last before the exit.
    u64 = u.to(tl.float64)
    j0 = tl.ceil(t_in.to(tl.float64) / step - u64)
    j1 = tl.ceil(t_out.to(tl.float64) / step - u64)
    finite = (tl.abs(j0) < float("inf")) & (tl.abs(j1) < float("inf"))  # (NaN fails both)
    bad = ~hit | ~finite | (j1 - j0 > max_steps)
    j0 = tl.where(bad, 0.0, tl.minimum(tl.maximum(j0, -max_steps), max_steps))
    j1 = tl.where(bad, 0.0, tl.minimum(tl.maximum(j1, -max_steps), max_steps))
    j1 = tl.maximum(j0, j1)
    if HAS_BG:
        cx = tl.load(center_ptr)
        cy = tl.load(center_ptr + 1)
        cz = tl.load(center_ptr + 2)
        rx = far_radius / tl.load(inv_half_ptr)
        ry = far_radius / tl.load(inv_half_ptr + 1)
        rz = far_radius / tl.load(inv_half_ptr + 2)
        _, t_far = _ray_box(ox, oy, oz, ix, iy, iz, cx - rx, cy - ry, cz - rz, cx + rx, cy + ry, cz + rz)
        t_far = tl.where(tl.abs(t_far) < float("inf"), t_far, near)
        t_in = tl.where(hit, t_in, t_far)
        t_out = tl.where(hit, t_out, t_far)
        phase = tl.where(t_far > near, PHASE_BEFORE, PHASE_DONE)
    else:
        t_far = t_out
        phase = tl.where(hit, PHASE_INNER, PHASE_DONE)
    tl.store(phase_ptr + rays, phase.to(tl.int8), mask=valid)
    tl.store(j_ptr + rays, j0.to(tl.int64), mask=valid)
    tl.store(j_end_ptr + rays, j1.to(tl.int64), mask=valid)
    tl.store(t_ptr + rays, tl.zeros_like(t_in) + near, mask=valid)
    tl.store(t_in_ptr + rays, t_in, mask=valid)
    tl.store(t_out_ptr + rays, t_out, mask=valid)
    tl.store(t_far_ptr + rays, t_far, mask=valid)


def march_setup(o, d, u, box, g, near: float, max_steps: int, far_radius: float):
    """renderer.march_setup's state in one kernel, given the offsets u and the occupied bounds `box` (2, 3):
    (phase, j, j_end, t, t_in, t_out, t_far)."""
    n, dev = o.shape[0], o.device
    f32 = dict(dtype=torch.float32, device=dev)
    phase = torch.empty(n, dtype=torch.int8, device=dev)
    j, j_end = torch.empty(n, dtype=torch.int64, device=dev), torch.empty(n, dtype=torch.int64, device=dev)
    t, t_in, t_out, t_far = (torch.empty(n, **f32) for _ in range(4))
    if n:
        center, inv_half = (g.center, g.inv_half) if g.has_bg else (g.lo, g.scale)
        with kernel_launch("march_setup"):
            _setup[(triton.cdiv(n, BLOCK),)](
                o.contiguous(),
                d.contiguous(),
                u,
                box.contiguous(),
                center,
                inv_half,
                phase,
                j,
                j_end,
                t,
                t_in,
                t_out,
                t_far,
                n,
                float(near),
                float(g.step),
                float(max_steps),
                float(far_radius),
                HAS_BG=bool(g.has_bg),
                BLOCK=BLOCK,
            )
    return phase, j, j_end, t, t_in, t_out, t_far


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
            o.contiguous(),
            d.contiguous(),
            alive.contiguous(),
            active.contiguous().view(torch.uint8),
            s.phase,
            s.j,
            s.t,
            s.j_end,
            s.u,
            s.t_in,
            s.t_out,
            s.t_far,
            ts,
            dts,
            counts,
            g.lo,
            g.scale,
            mask,
            center,
            inv_half,
            bg_mask,
            n,
            k,
            n_blocks,
            block_steps,
            bg_per_block,
            g.res,
            float(g.step),
            bg_res,
            float(bg_quarter),
            float(bg_step),
            HAS_BG=bool(g.has_bg),
            BLOCK=BLOCK,
        )
    return ts, dts, counts
