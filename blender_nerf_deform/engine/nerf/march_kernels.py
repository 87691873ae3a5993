"""Ray marching in rounds: the next samples of each live ray, in occupied cells, on CPU (numba) or torch.

A ray runs through up to three segments: the background before the inner grid's box,
the box itself, the background after it (the background segments only for unbounded
NeRFs, whose `ContractedGrid` covers all space outside the inner box). In the box the
samples lie on the lattice t = (j + u) * step measured from the ray's origin (so which
grid clips the ray does not move them); in the background the step grows with the
distance from the inner box (instant-ngp's cone stepping, measured from the box centre:
dt = bg_step * max(1, |u|_inf) with u in inner-box units), one sample per step at the
fraction u of the step.

`march_round` emits at most `k` occupied samples per live ray and remembers where
each ray stopped (`MarchState`), so the renderer can evaluate those samples, retire
rays whose transmittance is spent, and march on only the others: early termination
that works in scenes that are full everywhere (real captures), where marching every
ray to its end first cost ~7x the samples that can be seen.

Why kernels: the torch formulation materialises candidate samples before the
occupancy test; the kernel walks each ray once and writes only the kept samples.
Both give the same samples (same float32 operations, no fused multiply-add).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .. import backend

# No fused multiply-add ("contract"): the torch path must find the same samples. No no-NaN /
# no-inf assumptions either, which would let LLVM drop the tests that keep a NaN or infinite
# sample (a NaN box, a wild ray) from becoming an out-of-bounds mask index.
FAST = {"nsz", "arcp", "afn", "reassoc"}
MAX_STEPS_PER_RAY = 1 << 31  # a ray longer than this many steps is no ray of a finite scene
PHASE_BEFORE, PHASE_INNER, PHASE_AFTER, PHASE_DONE = 0, 1, 2, 3


@dataclass
class MarchState:
    """Where each ray of a chunk stands: phase, next lattice index, next background t, and its fixed
    segment ends (entry/exit of the inner box, lattice index range, far end)."""

    phase: torch.Tensor  # int8 (R,)
    j: torch.Tensor  # int64 (R,) next lattice index in the box
    j_end: torch.Tensor  # int64 (R,) one past the box's last lattice index
    t: torch.Tensor  # float32 (R,) next background position
    t_in: torch.Tensor
    t_out: torch.Tensor
    t_far: torch.Tensor
    u: torch.Tensor  # float32 (R,) sample offset in [0, 1)


@dataclass
class Grids:
    """What the march reads of the occupancy grids, as flat arrays."""

    lo: torch.Tensor  # inner grid: world box corner (3,)
    scale: torch.Tensor  # cells per world unit (3,)
    res: int
    mask: torch.Tensor  # bool (res^3,)
    step: float
    has_bg: bool = False
    center: torch.Tensor | None = None  # background: inner box centre and 1 / half-size (3,)
    inv_half: torch.Tensor | None = None
    bg_res: int = 1
    bg_mask: torch.Tensor | None = None
    bg_step: float = 1.0
    coarse: torch.Tensor | None = None  # bool (cr^3,): blocks of COARSE^3 inner cells holding any occupied one
    coarse_res: int = 0


# The numba march jumps over empty blocks of COARSE^3 cells of the inner grid (to the last lattice
# sample before the block's exit, minus one for rounding): it emits the same samples as stepping
# through them one lattice step at a time (the torch path still does), in fewer steps.
COARSE = 8


def coarse_mask(mask: torch.Tensor, res: int) -> tuple[torch.Tensor, int]:
    """(bool (cr^3,) flat x-fastest, cr): whether each block of COARSE^3 cells holds an occupied cell."""
    cr = (res + COARSE - 1) // COARSE
    m = mask.reshape(res, res, res)
    pad = cr * COARSE - res
    if pad:
        m = torch.nn.functional.pad(m, (0, pad, 0, pad, 0, pad))
    blocks = m.reshape(cr, COARSE, cr, COARSE, cr, COARSE).any(dim=5).any(dim=3).any(dim=1)
    return blocks.reshape(-1).contiguous(), cr


if backend.HAVE_NUMBA:
    from ..kernel_cache import njit, prange

    @njit(inline="always", fastmath=FAST)
    def _inner_occupied(px, py, pz, lo, scale, r, mask):
        fx = np.floor((px - lo[0]) * scale[0])
        fy = np.floor((py - lo[1]) * scale[1])
        fz = np.floor((pz - lo[2]) * scale[2])
        if not (fx >= 0 and fy >= 0 and fz >= 0 and fx < r and fy < r and fz < r):
            return False  # outside the grid, or NaN (every comparison with NaN is False)
        return mask[int(fx) + r * int(fy) + r * r * int(fz)] != 0

    @njit(inline="always", fastmath=FAST)
    def _radius(px, py, pz, center, inv_half):
        """|u|_inf of a world point in inner-box units, at least 1 (NaN → 1)."""
        m = max(
            abs((px - center[0]) * inv_half[0]),
            abs((py - center[1]) * inv_half[1]),
            abs((pz - center[2]) * inv_half[2]),
        )
        if not (m > np.float32(1.0)):
            m = np.float32(1.0)
        return m

    @njit(inline="always", fastmath=FAST)
    def _bg_occupied(px, py, pz, center, inv_half, r, mask):
        ux = (px - center[0]) * inv_half[0]
        uy = (py - center[1]) * inv_half[1]
        uz = (pz - center[2]) * inv_half[2]
        m = max(abs(ux), abs(uy), abs(uz))
        s = np.float32(1.0)
        if m > np.float32(1.0):
            s = (np.float32(2.0) - np.float32(1.0) / m) / m
        cs = np.float32(r) / np.float32(4.0)
        fx = np.floor((ux * s + np.float32(2.0)) * cs)
        fy = np.floor((uy * s + np.float32(2.0)) * cs)
        fz = np.floor((uz * s + np.float32(2.0)) * cs)
        if not (fx >= 0 and fy >= 0 and fz >= 0 and fx < r and fy < r and fz < r):
            return False
        return mask[int(fx) + r * int(fy) + r * r * int(fz)] != 0

    @njit(inline="always", fastmath=FAST)
    def _slab_exit(p, d, lo, scale, f):
        """Distance along d from p (inside block f of an axis) to where the ray leaves the block."""
        if abs(d) <= 1e-12:
            return 1e30
        size = np.float64(COARSE) / np.float64(scale)
        face = np.float64(lo) + (np.float64(f) + (1.0 if d > 0 else 0.0)) * size
        return (face - np.float64(p)) / np.float64(d)

    @njit(inline="always", fastmath=FAST)
    def _skip_empty_block(px, py, pz, dx, dy, dz, lo, scale, coarse, cr, ts_, step, ur, j):
        """The next lattice index to test: past the empty COARSE^3 block holding the point, or j + 1."""
        # The block of the point's own cell (as _inner_occupied floors it), so the block holds the point.
        cx = np.floor((px - lo[0]) * scale[0])
        cy = np.floor((py - lo[1]) * scale[1])
        cz = np.floor((pz - lo[2]) * scale[2])
        if not (cx >= 0 and cy >= 0 and cz >= 0 and cx < cr * COARSE and cy < cr * COARSE and cz < cr * COARSE):
            return j + 1
        bx, by, bz = int(cx) // COARSE, int(cy) // COARSE, int(cz) // COARSE
        if coarse[bx + cr * by + cr * cr * bz] != 0:
            return j + 1
        fx, fy, fz = np.float64(bx), np.float64(by), np.float64(bz)
        # Exit distance from the block along the ray (slab test, from the point), in float64.
        t_exit = min(
            _slab_exit(px, dx, lo[0], scale[0], fx),
            _slab_exit(py, dy, lo[1], scale[1], fy),
            _slab_exit(pz, dz, lo[2], scale[2], fz),
        )
        if not (t_exit < 1e29) or t_exit <= 0:
            return j + 1
        jn = np.int64(np.floor((np.float64(ts_) + t_exit) / np.float64(step) - np.float64(ur))) - 1
        return jn if jn > j + 1 else j + 1

    @njit(parallel=True, cache=True, fastmath=FAST)
    def _march_round(
        o,
        d,
        alive,
        phase,
        jn,
        j_end,
        tb,
        t_in,
        t_out,
        t_far,
        u,
        k,
        lo,
        scale,
        r,
        mask,
        step,
        has_bg,
        center,
        inv_half,
        bg_r,
        bg_mask,
        bg_step,
        ts,
        dts,
        counts,
        coarse,
        cr,
    ):
        for a in prange(alive.shape[0]):
            ray = alive[a]
            n = 0
            ox, oy, oz = o[ray, 0], o[ray, 1], o[ray, 2]
            dx, dy, dz = d[ray, 0], d[ray, 1], d[ray, 2]
            ur = u[ray]
            ph = phase[ray]
            j = jn[ray]
            t = tb[ray]
            guard = 0
            while n < k and ph < 3 and guard < MAX_STEPS_PER_RAY:
                guard += 1
                if ph == 1:
                    if j >= j_end[ray]:
                        if has_bg:
                            ph = 2
                            t = t_out[ray]
                        else:
                            ph = 3
                        continue
                    ts_ = (np.float32(j) + ur) * step
                    px, py, pz = ox + dx * ts_, oy + dy * ts_, oz + dz * ts_
                    if _inner_occupied(px, py, pz, lo, scale, r, mask):
                        ts[a, n] = ts_
                        dts[a, n] = step
                        n += 1
                        j += 1
                    elif cr > 0:
                        j = _skip_empty_block(px, py, pz, dx, dy, dz, lo, scale, coarse, cr, ts_, step, ur, j)
                    else:
                        j += 1
                else:
                    end = t_in[ray] if ph == 0 else t_far[ray]
                    if not (t < end):
                        ph = 1 if ph == 0 else 3
                        continue
                    dt = bg_step * _radius(ox + dx * t, oy + dy * t, oz + dz * t, center, inv_half)
                    t_next = t + dt
                    if not (t_next < end):
                        t_next = end
                    ts_ = t + ur * (t_next - t)
                    if _bg_occupied(ox + dx * ts_, oy + dy * ts_, oz + dz * ts_, center, inv_half, bg_r, bg_mask):
                        ts[a, n] = ts_
                        dts[a, n] = t_next - t
                        n += 1
                    t = t_next
            phase[ray] = ph
            jn[ray] = j
            tb[ray] = t
            counts[a] = n

    @njit(parallel=True, cache=True)
    def _gather_samples(o, d, alive, ts, dts, counts, starts, ray_out, t_out, dt_out, p_out, dir_out):
        # No fastmath: o + d * t rounds as torch's separate multiply and add do (same sample positions).
        for a in prange(alive.shape[0]):
            ray = alive[a]
            s0 = starts[a]
            for j in range(counts[a]):
                s = s0 + j
                t = ts[a, j]
                ray_out[s] = ray
                t_out[s] = t
                dt_out[s] = dts[a, j]
                for c in range(3):
                    p_out[s, c] = o[ray, c] + d[ray, c] * t
                    dir_out[s, c] = d[ray, c]


def _np(x):
    return x.contiguous().numpy()


def gather_samples(o, d, alive, ts, dts, counts):
    """The samples of one round, flat and sorted by ray then t: (ray index, t, dt, position o + t d, direction).

    `ts`, `dts` (A, k) and `counts` (A,) as `march_round` returns them for the rays `alive`."""
    if backend.use_kernels(o.device) and ts.device.type == "cpu":
        counts_np = counts.numpy()
        starts = np.cumsum(counts_np) - counts_np
        n = int(counts_np.sum())
        ray = np.empty(n, np.int64)
        t, dt = np.empty(n, np.float32), np.empty(n, np.float32)
        p, v = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        _gather_samples(_np(o), _np(d), _np(alive), ts.numpy(), dts.numpy(), counts_np, starts, ray, t, dt, p, v)
        return (
            torch.from_numpy(ray),
            torch.from_numpy(t),
            torch.from_numpy(dt),
            torch.from_numpy(p),
            torch.from_numpy(v),
        )
    dev = o.device
    k = ts.shape[1]
    valid = torch.arange(k, device=dev)[None, :] < counts.to(dev)[:, None]
    a, slot = torch.nonzero(valid, as_tuple=True)
    ray = alive[a]
    t = ts.to(dev)[a, slot]
    return ray, t, dts.to(dev)[a, slot], o[ray] + d[ray] * t[:, None], d[ray]


def _march_round_cpu(o, d, alive, state: MarchState, k: int, g: Grids):
    n = alive.shape[0]
    ts = np.empty((n, k), np.float32)
    dts = np.empty((n, k), np.float32)
    counts = np.empty(n, np.int64)
    ones = np.ones(3, np.float32)
    _march_round(
        _np(o),
        _np(d),
        _np(alive),
        state.phase.numpy(),
        state.j.numpy(),
        _np(state.j_end),
        state.t.numpy(),
        _np(state.t_in),
        _np(state.t_out),
        _np(state.t_far),
        _np(state.u),
        int(k),
        _np(g.lo),
        _np(g.scale),
        g.res,
        g.mask.numpy().view(np.uint8),
        np.float32(g.step),
        g.has_bg,
        _np(g.center) if g.has_bg else ones,
        _np(g.inv_half) if g.has_bg else ones,
        g.bg_res,
        g.bg_mask.numpy().view(np.uint8) if g.has_bg else np.zeros(1, np.uint8),
        np.float32(g.bg_step),
        ts,
        dts,
        counts,
        g.coarse.numpy().view(np.uint8) if g.coarse is not None else np.zeros(1, np.uint8),
        g.coarse_res if g.coarse is not None else 0,
    )
    return torch.from_numpy(ts), torch.from_numpy(dts), torch.from_numpy(counts)


def _inner_occupied_torch(p, g: Grids):
    f = torch.floor((p - g.lo) * g.scale)
    inside = ((f >= 0) & (f < g.res)).all(dim=-1)
    f = torch.where(inside[:, None], f, torch.zeros_like(f)).long()
    return inside & g.mask[f[:, 0] + g.res * f[:, 1] + g.res * g.res * f[:, 2]]


def _radius_torch(p, g: Grids):
    m = ((p - g.center) * g.inv_half).abs().amax(dim=-1)
    return torch.where(m > 1.0, m, torch.ones_like(m))


def _bg_occupied_torch(p, g: Grids):
    uu = (p - g.center) * g.inv_half
    m = uu.abs().amax(dim=-1, keepdim=True)
    s = torch.where(m > 1.0, (2.0 - 1.0 / m) / m, torch.ones_like(m))
    f = torch.floor((uu * s + 2.0) * (g.bg_res / 4.0))
    inside = ((f >= 0) & (f < g.bg_res)).all(dim=-1)
    f = torch.where(inside[:, None], f, torch.zeros_like(f)).long()
    return inside & g.bg_mask[f[:, 0] + g.bg_res * f[:, 1] + g.bg_res * g.bg_res * f[:, 2]]


def _march_round_torch(o, d, alive, s: MarchState, k: int, g: Grids, block: int = 64):
    """The kernel's walk, vectorised over rays: box segments `block` lattice steps at a time, background
    segments one step at a time (they take few steps: the step grows with distance)."""
    dev = o.device
    n = alive.shape[0]
    ts = torch.zeros((n, k), dtype=torch.float32, device=dev)
    dts = torch.zeros((n, k), dtype=torch.float32, device=dev)
    counts = torch.zeros(n, dtype=torch.int64, device=dev)
    offsets = torch.arange(block, device=dev)
    while True:
        ph = s.phase[alive]
        active = (counts < k) & (ph < PHASE_DONE)
        if not bool(active.any()):
            break
        # Box segment.
        a = torch.nonzero(active & (ph == PHASE_INNER)).flatten()
        if a.numel():
            ray = alive[a]
            j = s.j[ray][:, None] + offsets  # (A, B)
            valid = j < s.j_end[ray][:, None]
            t = (j.float() + s.u[ray][:, None]) * g.step
            p = o[ray][:, None, :] + d[ray][:, None, :] * t[..., None]
            occ = _inner_occupied_torch(p.reshape(-1, 3), g).reshape(valid.shape) & valid
            room = (k - counts[a])[:, None]
            rank = torch.cumsum(occ.long(), dim=1)
            take = occ & (rank <= room)
            r_, c_ = torch.nonzero(take, as_tuple=True)
            slot = counts[a][r_] + rank[r_, c_] - 1
            ts[a[r_], slot] = t[r_, c_]
            dts[a[r_], slot] = g.step
            taken = take.sum(dim=1)
            full = counts[a] + taken >= k
            # A full ray resumes after its last sample; the others after the block (or at the end).
            last = torch.where(take, offsets.expand_as(take), torch.full_like(take, -1, dtype=torch.int64)).amax(dim=1)
            nxt = torch.where(full, s.j[ray] + last + 1, torch.minimum(s.j[ray] + block, s.j_end[ray]))
            s.j[ray] = nxt
            counts[a] += taken
            done_box = (nxt >= s.j_end[ray]) & ~full
            if bool(done_box.any()):
                rd = ray[done_box]
                s.phase[rd] = PHASE_AFTER if g.has_bg else PHASE_DONE
                if g.has_bg:
                    s.t[rd] = s.t_out[rd]
        # Background segments.
        b = torch.nonzero(active & ((ph == PHASE_BEFORE) | (ph == PHASE_AFTER))).flatten()
        if b.numel():
            ray = alive[b]
            before = s.phase[ray] == PHASE_BEFORE
            end = torch.where(before, s.t_in[ray], s.t_far[ray])
            t = s.t[ray]
            over = ~(t < end)
            if bool(over.any()):
                ro = ray[over]
                s.phase[ro] = torch.where(
                    before[over], torch.full_like(s.phase[ro], PHASE_INNER), torch.full_like(s.phase[ro], PHASE_DONE)
                )
            go = ~over
            b, ray, t, end = b[go], ray[go], t[go], end[go]
            if b.numel():
                o_r, d_r = o[ray], d[ray]
                dt = g.bg_step * _radius_torch(o_r + d_r * t[:, None], g)
                t_next = t + dt
                t_next = torch.where(t_next < end, t_next, end)
                tsam = t + s.u[ray] * (t_next - t)
                occ = _bg_occupied_torch(o_r + d_r * tsam[:, None], g)
                hit = torch.nonzero(occ).flatten()
                ts[b[hit], counts[b[hit]]] = tsam[hit]
                dts[b[hit], counts[b[hit]]] = (t_next - t)[hit]
                counts[b[hit]] += 1
                s.t[ray] = t_next
    return ts, dts, counts


def march_round_device(
    o,
    d,
    alive,
    active,
    s: MarchState,
    k: int,
    g: Grids,
    box_steps: int,
    block: int = 128,
    bg_per_block: int = 8,
    settle: bool = False,
):
    """`march_round` without a host-device sync (the device path): up to k next samples of each ray in `alive`
    whose `active` is True (the others emit none and stay where they are); (t (A, k), dt (A, k), counts (A,)).

    Every loop runs a count fixed on the host: ceil(box_steps / block) blocks of `block` lattice steps (a box
    segment is at most `box_steps` long, so a ray's box segment ends within one round unless it fills k), each
    followed by `bg_per_block` background steps; a ray whose background is longer goes on next round. No
    compaction: rays that are done or full are masked, and samples past the k-th are written to a spare column.
    The same samples as `march_round` (the same float32 operations in the same order per ray). Where Triton
    runs (`backend.use_triton`), one kernel with the same step budget (march_triton.py), which leaves its loops
    on the device once no ray is in them. The torch formulation does so with `settle` only: a read back per
    block (what marching every block for every ray costs on the CPU, where frames render on this formulation
    in the tests, is far more than the read)."""
    if backend.use_triton(o.device):
        from . import march_triton

        return march_triton.march_round(
            o, d, alive, active, s, k, g, max(1, -(-box_steps // block)), block, bg_per_block
        )
    dev = o.device
    n = alive.shape[0]
    ts = torch.zeros((n, k + 1), dtype=torch.float32, device=dev)
    dts = torch.zeros((n, k + 1), dtype=torch.float32, device=dev)
    counts = torch.zeros(n, dtype=torch.int64, device=dev)
    offsets = torch.arange(block, device=dev)
    o_r, d_r = o[alive], d[alive]
    ph, j, t_bg = s.phase[alive], s.j[alive], s.t[alive]
    j_end, u = s.j_end[alive], s.u[alive]
    t_in, t_out, t_far = s.t_in[alive], s.t_out[alive], s.t_far[alive]
    step = torch.tensor(g.step, dtype=torch.float32, device=dev)
    after = PHASE_AFTER if g.has_bg else PHASE_DONE
    for _ in range(max(1, -(-box_steps // block))):
        if settle and not bool((active & (ph < PHASE_DONE) & (counts < k)).any()):
            break
        inner = active & (ph == PHASE_INNER) & (counts < k)
        jj = j[:, None] + offsets  # (A, B)
        valid = (jj < j_end[:, None]) & inner[:, None]
        t = (jj.float() + u[:, None]) * g.step
        p = o_r[:, None, :] + d_r[:, None, :] * t[..., None]
        occ = _inner_occupied_torch(p.reshape(-1, 3), g).reshape(valid.shape) & valid
        rank = torch.cumsum(occ.long(), dim=1)
        take = occ & (rank <= (k - counts)[:, None])
        slot = torch.where(take, counts[:, None] + rank - 1, k)
        ts.scatter_(1, slot, t)
        dts.scatter_(1, slot, step.expand(slot.shape))
        taken = take.sum(dim=1)
        full = counts + taken >= k
        # A full ray resumes after its last sample; the others after the block (or at the end).
        last = torch.where(take, offsets, -1).amax(dim=1)
        nxt = torch.where(full, j + last + 1, torch.minimum(j + block, j_end))
        j = torch.where(inner, nxt, j)
        counts = counts + taken
        done_box = inner & (nxt >= j_end) & ~full
        ph = torch.where(done_box, after, ph)
        if not g.has_bg:
            continue
        t_bg = torch.where(done_box, t_out, t_bg)
        for _ in range(bg_per_block):
            bg = active & ((ph == PHASE_BEFORE) | (ph == PHASE_AFTER)) & (counts < k)
            before = ph == PHASE_BEFORE
            end = torch.where(before, t_in, t_far)
            over = bg & ~(t_bg < end)
            ph = torch.where(over, torch.where(before, PHASE_INNER, PHASE_DONE), ph).to(torch.int8)
            go = bg & ~over
            dt = g.bg_step * _radius_torch(o_r + d_r * t_bg[:, None], g)
            t_next = t_bg + dt
            t_next = torch.where(t_next < end, t_next, end)
            tsam = t_bg + u * (t_next - t_bg)
            hit = _bg_occupied_torch(o_r + d_r * tsam[:, None], g) & go
            slot = torch.where(hit, counts, k)[:, None]
            ts.scatter_(1, slot, tsam[:, None])
            dts.scatter_(1, slot, (t_next - t_bg)[:, None])
            counts = counts + hit
            t_bg = torch.where(go, t_next, t_bg)
    s.phase[alive], s.j[alive], s.t[alive] = ph.to(torch.int8), j, t_bg
    return ts[:, :k], dts[:, :k], counts


def march_round(o, d, alive, state: MarchState, k: int, grids: Grids):
    """Up to k next samples of each ray in `alive`: (t (A, k), dt (A, k), counts (A,)); `state` advances."""
    if backend.use_kernels(o.device) and grids.mask.device.type == "cpu":
        return _march_round_cpu(o, d, alive, state, k, grids)
    return _march_round_torch(o, d, alive, state, k, grids)
