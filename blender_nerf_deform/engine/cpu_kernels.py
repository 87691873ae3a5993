"""Fused CPU kernels (numba) for the hash encoding: the forward gather and the backward scatter-add.

Why: on CPU the torch formulation of the encoding materialises (N, L, 8, 3)
int64 index tensors and (N, L, 8, F) gathered features; it is memory-bound and
runs at ~0.1-0.4 M points/s on the project's 2-core machine (BENCHMARKS.md).
These kernels compute each point's indices, weights and features in registers
and write only the (N, L*F) output: forward parallel over points, backward
parallel over levels (levels own disjoint table rows, so no atomics are needed).

The kernels are used only for CPU tensors whose positions do not require
gradients; CUDA (and any other case) takes the torch path of `hashgrid.py`, so
the same model runs everywhere. numba is optional: without it the torch path
runs on CPU too, only slower.
"""

from __future__ import annotations

import numpy as np
import torch

try:  # numba is an optional accelerator, pinned in requirements.txt.
    import numba
    from numba import njit, prange

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    HAVE_NUMBA = False


if HAVE_NUMBA:

    @njit(cache=True, fastmath=False, inline="always")
    def _row(cx, cy, cz, res, dense, size, offset):
        if dense:
            if cx > res:
                cx = res
            if cy > res:
                cy = res
            if cz > res:
                cz = res
            return offset + cx + cy * (res + 1) + cz * (res + 1) * (res + 1)
        # int64 arithmetic: the low 32 bits equal instant-ngp's uint32 hash, and size is a power of two.
        return offset + ((cx ^ (cy * 2654435761) ^ (cz * 805459861)) & (size - 1))

    @njit(parallel=True, cache=True, fastmath=True)
    def _hash_forward(x, table, res_arr, dense_arr, size_arr, off_arr, out):
        # Blocks of points in parallel; inside a block, level by level, so that the rows one
        # level touches (at most 2^log2T x F floats) stay in cache while the block is served.
        n = x.shape[0]
        n_levels = res_arr.shape[0]
        nf = table.shape[1]
        block = 2048
        n_blocks = (n + block - 1) // block
        for b in prange(n_blocks):
            start = b * block
            stop = min(n, start + block)
            for lvl in range(n_levels):
                res = res_arr[lvl]
                dense = dense_arr[lvl]
                size = size_arr[lvl]
                off = off_arr[lvl]
                for i in range(start, stop):
                    fx = min(max(x[i, 0], 0.0), 1.0) * res
                    fy = min(max(x[i, 1], 0.0), 1.0) * res
                    fz = min(max(x[i, 2], 0.0), 1.0) * res
                    bx = np.int64(np.floor(fx))
                    by = np.int64(np.floor(fy))
                    bz = np.int64(np.floor(fz))
                    tx = fx - bx
                    ty = fy - by
                    tz = fz - bz
                    for f in range(nf):
                        out[i, lvl * nf + f] = 0.0
                    for c in range(8):
                        ox = c & 1
                        oy = (c >> 1) & 1
                        oz = (c >> 2) & 1
                        w = (tx if ox else 1.0 - tx) * (ty if oy else 1.0 - ty) * (tz if oz else 1.0 - tz)
                        row = _row(bx + ox, by + oy, bz + oz, res, dense, size, off)
                        for f in range(nf):
                            out[i, lvl * nf + f] += w * table[row, f]

    @njit(parallel=True, cache=True, fastmath=True)
    def _hash_backward(x, grad_out, res_arr, dense_arr, size_arr, off_arr, grad_table, touched):
        n = x.shape[0]
        n_levels = res_arr.shape[0]
        nf = grad_table.shape[1]
        for lvl in prange(n_levels):
            res = res_arr[lvl]
            dense = dense_arr[lvl]
            size = size_arr[lvl]
            off = off_arr[lvl]
            for i in range(n):
                fx = min(max(x[i, 0], 0.0), 1.0) * res
                fy = min(max(x[i, 1], 0.0), 1.0) * res
                fz = min(max(x[i, 2], 0.0), 1.0) * res
                bx = np.int64(np.floor(fx))
                by = np.int64(np.floor(fy))
                bz = np.int64(np.floor(fz))
                tx = fx - bx
                ty = fy - by
                tz = fz - bz
                for c in range(8):
                    ox = c & 1
                    oy = (c >> 1) & 1
                    oz = (c >> 2) & 1
                    w = (tx if ox else 1.0 - tx) * (ty if oy else 1.0 - ty) * (tz if oz else 1.0 - tz)
                    row = _row(bx + ox, by + oy, bz + oz, res, dense, size, off)
                    touched[row] = 1
                    for f in range(nf):
                        grad_table[row, f] += w * grad_out[i, lvl * nf + f]

    @njit(parallel=True, cache=True, fastmath=True)
    def _sparse_adam(param, grad, m, v, touched, lr, b1, b2, eps, bc1, bc2):
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


def kernels_apply(x: torch.Tensor, table: torch.Tensor) -> bool:
    """Whether the fused CPU kernels can run these tensors (CPU float32, positions without grad)."""
    return (HAVE_NUMBA and x.device.type == "cpu" and table.device.type == "cpu"
            and table.dtype == torch.float32 and not x.requires_grad)


class _LevelArrays:
    """Per-level constants of a HashEncoding as numpy arrays for the kernels (cached on the encoding)."""

    def __init__(self, enc):
        self.res = np.asarray(enc.resolutions, dtype=np.int64)
        self.dense = np.asarray(enc.dense_levels, dtype=np.bool_)
        self.size = np.asarray(enc.level_sizes, dtype=np.int64)
        self.off = np.cumsum([0] + list(enc.level_sizes[:-1])).astype(np.int64)


class HashEncodeCPU(torch.autograd.Function):
    """Fused hash encoding on CPU: gradients flow to the table only (positions are data)."""

    @staticmethod
    def forward(ctx, x, table, enc):
        arrs = enc._kernel_arrays
        xn = x.detach().contiguous().numpy()
        out = torch.empty(x.shape[0], enc.n_levels * enc.n_features, dtype=torch.float32)
        _hash_forward(xn, table.detach().numpy(), arrs.res, arrs.dense, arrs.size, arrs.off, out.numpy())
        ctx.save_for_backward(x)
        ctx.enc = enc
        return out

    @staticmethod
    def backward(ctx, grad_out):
        (x,) = ctx.saved_tensors
        enc = ctx.enc
        arrs = enc._kernel_arrays
        grad_table = enc.grad_buffer()
        _hash_backward(x.contiguous().numpy(), grad_out.contiguous().numpy(), arrs.res, arrs.dense, arrs.size,
                       arrs.off, grad_table.numpy(), enc.touched_rows())
        # In fused-grad mode the gradient stays in the encoding's buffer for the lazy Adam.
        return None, (None if enc.fused_grad else grad_table), None
