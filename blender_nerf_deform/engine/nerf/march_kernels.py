"""Ray marching on CPU (numba): the samples of each ray that fall in occupied cells of the grid.

Why: the torch formulation materialises every candidate sample of every ray
before the occupancy test; these kernels count, then fill, only the kept ones
(two passes, parallel over rays). `renderer.march` uses them when
`backend.use_kernels` says so; the torch path gives the same samples.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import backend

# fastmath without its no-NaN / no-inf assumptions, which would let LLVM drop the tests that keep
# a NaN or infinite sample (a NaN box, a wild ray) from becoming an out-of-bounds mask index.
FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}
MAX_STEPS_PER_RAY = 1 << 31  # a ray longer than this many steps is no ray of a finite scene

if backend.HAVE_NUMBA:
    from numba import njit, prange

    @njit(inline="always", fastmath=FAST)
    def _occupied_at(o, d, ray, t, lo, scale, r, mask):
        """Whether the sample at t lies in an occupied cell; False outside the grid (as OccupancyGrid.occupied),
        and for non-finite coordinates (every comparison with NaN is False)."""
        fx = np.floor((o[ray, 0] + d[ray, 0] * t - lo[0]) * scale[0])
        fy = np.floor((o[ray, 1] + d[ray, 1] * t - lo[1]) * scale[1])
        fz = np.floor((o[ray, 2] + d[ray, 2] * t - lo[2]) * scale[2])
        if not (fx >= 0 and fy >= 0 and fz >= 0 and fx < r and fy < r and fz < r):
            return False
        return mask[int(fx) + r * int(fy) + r * r * int(fz)] != 0

    @njit(inline="always", fastmath=FAST)
    def _steps(t0, t1, step):
        """Lattice steps between t0 and t1; 0 for NaN or absurd spans (the float-to-int cast would be undefined)."""
        span = np.ceil((t1 - t0) / step)
        if not (span > 0 and span < MAX_STEPS_PER_RAY):
            return 0
        return int(span)

    @njit(parallel=True, cache=True, fastmath=FAST)
    def _march_count(o, d, t0, t1, u, step, lo, scale, r, mask, counts):
        for ray in prange(o.shape[0]):
            n = 0
            k_max = _steps(t0[ray], t1[ray], step)
            for k in range(k_max):
                t = t0[ray] + (k + u[ray]) * step
                if t >= t1[ray]:
                    break
                if _occupied_at(o, d, ray, t, lo, scale, r, mask):
                    n += 1
            counts[ray] = n

    @njit(parallel=True, cache=True, fastmath=FAST)
    def _march_fill(o, d, t0, t1, u, step, lo, scale, r, mask, starts, rays, ray_idx, ts):
        for ray in prange(o.shape[0]):
            n = starts[ray]
            k_max = _steps(t0[ray], t1[ray], step)
            for k in range(k_max):
                t = t0[ray] + (k + u[ray]) * step
                if t >= t1[ray]:
                    break
                if _occupied_at(o, d, ray, t, lo, scale, r, mask):
                    ray_idx[n] = rays[ray]
                    ts[n] = t
                    n += 1


def march_cpu(o, d, t0, t1, u, step, occupancy, rays):
    """Samples in occupied cells, as renderer.march: (ray index, t), sorted by ray then t."""
    on, dn = o.contiguous().numpy(), d.contiguous().numpy()
    t0n, t1n, un = t0.contiguous().numpy(), t1.contiguous().numpy(), u.contiguous().numpy()
    lo = occupancy.aabb[0].numpy().astype(np.float32)
    scale = (occupancy.resolution / (occupancy.aabb[1] - occupancy.aabb[0])).numpy().astype(np.float32)
    mask = occupancy.mask.numpy().view(np.uint8)
    counts = np.empty(on.shape[0], np.int64)
    _march_count(on, dn, t0n, t1n, un, np.float32(step), lo, scale, occupancy.resolution, mask, counts)
    starts = np.cumsum(counts) - counts
    total = int(counts.sum())
    ray_idx = np.empty(total, np.int64)
    ts = np.empty(total, np.float32)
    _march_fill(on, dn, t0n, t1n, un, np.float32(step), lo, scale, occupancy.resolution, mask, starts,
                rays.numpy(), ray_idx, ts)
    return torch.from_numpy(ray_idx), torch.from_numpy(ts)

