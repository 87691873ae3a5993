"""Fused CPU kernels (numba) for the hash encoding: the forward gather and the backward scatter-add.

Why: on CPU the torch formulation of the encoding materialises (N, L, 8, 3)
int64 index tensors and (N, L, 8, F) gathered features; it is memory-bound.
These kernels compute each point's indices, weights and features in registers
and write only the (N, L*F) output: forward parallel over points, backward
parallel over levels (levels own disjoint table rows, so no atomics are needed).

The kernels are used for CPU float32 tensors when `backend.use_kernels` says so
(positions that require a gradient, for camera pose refinement, get it from a third
kernel); CUDA (and any other case) takes the torch path of `encoding.py`, so the
same model runs everywhere.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import backend

if backend.HAVE_NUMBA:
    from ..kernel_cache import njit, prange


# fastmath without its no-NaN / no-inf assumptions: with them LLVM may drop the NaN test of
# `_unit` below, and a NaN position becomes an out-of-bounds row (a segfault, not an error).
FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}

if backend.HAVE_NUMBA:

    @njit(cache=True, fastmath=FAST, inline="always")
    def _unit(v):
        """v clamped to [0, 1], NaN to 0: every corner row then lies in its level's table."""
        if not v > 0.0:
            return 0.0
        if v > 1.0:
            return 1.0
        return v

    @njit(cache=True, fastmath=False, inline="always")
    def _corners(px, py, pz, res, dense, size, off):
        """The table rows (r0..r7) and trilinear weights (w0..w7) of the 8 corners of a point's cell at one
        level, corner c at offset (c & 1, c >> 1 & 1, c >> 2 & 1). Written out corner by corner (not a loop
        over c calling a row function): the shared terms of the 8 rows and weights are computed once,
        which makes both kernels faster."""
        fx = _unit(px) * res
        fy = _unit(py) * res
        fz = _unit(pz) * res
        bx = np.int64(np.floor(fx))
        by = np.int64(np.floor(fy))
        bz = np.int64(np.floor(fz))
        tx = fx - bx
        ty = fy - by
        tz = fz - bz
        if dense:
            # Clamped so that points on the upper face stay in the grid (their weight there is 0 or 1).
            s1 = res + 1
            s2 = s1 * s1
            x0, x1 = min(bx, res), min(bx + 1, res)
            y0, y1 = min(by, res) * s1, min(by + 1, res) * s1
            z0, z1 = min(bz, res) * s2, min(bz + 1, res) * s2
            r0, r1, r2, r3 = off + x0 + y0 + z0, off + x1 + y0 + z0, off + x0 + y1 + z0, off + x1 + y1 + z0
            r4, r5, r6, r7 = off + x0 + y0 + z1, off + x1 + y0 + z1, off + x0 + y1 + z1, off + x1 + y1 + z1
        else:
            # int64 arithmetic: the low 32 bits equal instant-ngp's uint32 hash, and size is a power of two.
            mask = size - 1
            x0, x1 = bx, bx + 1
            y0, y1 = by * 2654435761, (by + 1) * 2654435761
            z0, z1 = bz * 805459861, (bz + 1) * 805459861
            r0, r1 = off + ((x0 ^ y0 ^ z0) & mask), off + ((x1 ^ y0 ^ z0) & mask)
            r2, r3 = off + ((x0 ^ y1 ^ z0) & mask), off + ((x1 ^ y1 ^ z0) & mask)
            r4, r5 = off + ((x0 ^ y0 ^ z1) & mask), off + ((x1 ^ y0 ^ z1) & mask)
            r6, r7 = off + ((x0 ^ y1 ^ z1) & mask), off + ((x1 ^ y1 ^ z1) & mask)
        ux = 1.0 - tx
        uy = 1.0 - ty
        uz = 1.0 - tz
        a00, a10, a01, a11 = ux * uy, tx * uy, ux * ty, tx * ty
        return (
            r0,
            r1,
            r2,
            r3,
            r4,
            r5,
            r6,
            r7,
            a00 * uz,
            a10 * uz,
            a01 * uz,
            a11 * uz,
            a00 * tz,
            a10 * tz,
            a01 * tz,
            a11 * tz,
        )

    @njit(parallel=True, cache=True, fastmath=FAST)
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
                col = lvl * nf
                for i in range(start, stop):
                    r0, r1, r2, r3, r4, r5, r6, r7, w0, w1, w2, w3, w4, w5, w6, w7 = _corners(
                        x[i, 0], x[i, 1], x[i, 2], res, dense, size, off
                    )
                    if nf == 4:  # the trainer's configuration: a constant trip count the compiler unrolls
                        for f in range(4):
                            out[i, col + f] = (
                                w0 * table[r0, f]
                                + w1 * table[r1, f]
                                + w2 * table[r2, f]
                                + w3 * table[r3, f]
                                + w4 * table[r4, f]
                                + w5 * table[r5, f]
                                + w6 * table[r6, f]
                                + w7 * table[r7, f]
                            )
                    else:
                        for f in range(nf):
                            out[i, col + f] = (
                                w0 * table[r0, f]
                                + w1 * table[r1, f]
                                + w2 * table[r2, f]
                                + w3 * table[r3, f]
                                + w4 * table[r4, f]
                                + w5 * table[r5, f]
                                + w6 * table[r6, f]
                                + w7 * table[r7, f]
                            )

    @njit(parallel=True, cache=True, fastmath=FAST)
    def _hash_backward(x, grad_out, res_arr, dense_arr, size_arr, off_arr, grad_table, touched):
        n = x.shape[0]
        n_levels = res_arr.shape[0]
        nf = grad_table.shape[1]
        # Threads take levels in the order 0, L-1, 1, L-2, ...: prange splits the range in
        # contiguous parts, and this mixes cheap (dense, coarse) and costly (hashed) levels.
        for j in prange(n_levels):
            lvl = j // 2 if j % 2 == 0 else n_levels - 1 - j // 2
            res = res_arr[lvl]
            dense = dense_arr[lvl]
            size = size_arr[lvl]
            off = off_arr[lvl]
            col = lvl * nf
            for i in range(n):
                r0, r1, r2, r3, r4, r5, r6, r7, w0, w1, w2, w3, w4, w5, w6, w7 = _corners(
                    x[i, 0], x[i, 1], x[i, 2], res, dense, size, off
                )
                for f in range(nf):
                    g = grad_out[i, col + f]
                    grad_table[r0, f] += w0 * g
                    grad_table[r1, f] += w1 * g
                    grad_table[r2, f] += w2 * g
                    grad_table[r3, f] += w3 * g
                    grad_table[r4, f] += w4 * g
                    grad_table[r5, f] += w5 * g
                    grad_table[r6, f] += w6 * g
                    grad_table[r7, f] += w7 * g
                touched[r0] = 1
                touched[r1] = 1
                touched[r2] = 1
                touched[r3] = 1
                touched[r4] = 1
                touched[r5] = 1
                touched[r6] = 1
                touched[r7] = 1

    @njit(parallel=True, cache=True, fastmath=FAST)
    def _hash_backward_x(x, grad_out, table, res_arr, dense_arr, size_arr, off_arr, grad_x):
        """The gradient of the encoding's output with respect to the positions (camera pose refinement):
        per level, res times the trilinear weights' derivatives against the corners' features dotted
        with the output gradient; zero along an axis where the position was clamped into [0, 1].
        Blocks of points level by level, as the forward (its table rows stay in cache)."""
        n = x.shape[0]
        n_levels = res_arr.shape[0]
        nf = table.shape[1]
        block = 2048
        n_blocks = (n + block - 1) // block
        for b in prange(n_blocks):
            start = b * block
            stop = min(n, start + block)
            for i in range(start, stop):
                grad_x[i, 0] = 0.0
                grad_x[i, 1] = 0.0
                grad_x[i, 2] = 0.0
            for lvl in range(n_levels):
                res = res_arr[lvl]
                dense = dense_arr[lvl]
                size = size_arr[lvl]
                off = off_arr[lvl]
                col = lvl * nf
                for i in range(start, stop):
                    px, py, pz = x[i, 0], x[i, 1], x[i, 2]
                    r0, r1, r2, r3, r4, r5, r6, r7, w0, w1, w2, w3, w4, w5, w6, w7 = _corners(
                        px, py, pz, res, dense, size, off
                    )
                    # s_c: the output gradient dotted with corner c's features.
                    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
                    for f in range(nf):
                        g = grad_out[i, col + f]
                        s0 += g * table[r0, f]
                        s1 += g * table[r1, f]
                        s2 += g * table[r2, f]
                        s3 += g * table[r3, f]
                        s4 += g * table[r4, f]
                        s5 += g * table[r5, f]
                        s6 += g * table[r6, f]
                        s7 += g * table[r7, f]
                    tx = _unit(px) * res
                    ty = _unit(py) * res
                    tz = _unit(pz) * res
                    tx -= np.floor(tx)
                    ty -= np.floor(ty)
                    tz -= np.floor(tz)
                    ux = 1.0 - tx
                    uy = 1.0 - ty
                    uz = 1.0 - tz
                    # d(weight of corner c)/dt_a: the product of the other two axes' factors, signed by c's bit a.
                    grad_x[i, 0] += res * (
                        uy * uz * (s1 - s0) + ty * uz * (s3 - s2) + uy * tz * (s5 - s4) + ty * tz * (s7 - s6)
                    )
                    grad_x[i, 1] += res * (
                        ux * uz * (s2 - s0) + tx * uz * (s3 - s1) + ux * tz * (s6 - s4) + tx * tz * (s7 - s5)
                    )
                    grad_x[i, 2] += res * (
                        ux * uy * (s4 - s0) + tx * uy * (s5 - s1) + ux * ty * (s6 - s2) + tx * ty * (s7 - s3)
                    )
            for i in range(start, stop):
                if not 0.0 < x[i, 0] < 1.0:
                    grad_x[i, 0] = 0.0
                if not 0.0 < x[i, 1] < 1.0:
                    grad_x[i, 1] = 0.0
                if not 0.0 < x[i, 2] < 1.0:
                    grad_x[i, 2] = 0.0


def positions_grad(x: torch.Tensor, grad_out: torch.Tensor, enc) -> torch.Tensor:
    """dL/dx (N, 3) of the encoding at positions x given dL/d(encoding) (N, L*F), by `_hash_backward_x`."""
    arrs = enc._kernel_arrays
    grad_x = torch.empty(x.shape[0], 3, dtype=x.dtype)
    _hash_backward_x(
        x.detach().contiguous().numpy(),
        grad_out.contiguous().numpy(),
        enc.table.detach().numpy(),
        arrs.res,
        arrs.dense,
        arrs.size,
        arrs.off,
        grad_x.numpy(),
    )
    return grad_x


def kernels_apply(x: torch.Tensor, table: torch.Tensor) -> bool:
    """Whether the fused CPU kernels can run these tensors (a CPU float32 table)."""
    return backend.use_kernels(x.device) and table.device.type == "cpu" and table.dtype == torch.float32


class LevelArrays:
    """Per-level constants of a HashEncoding as numpy arrays for the kernels (cached on the encoding)."""

    def __init__(self, enc):
        self.res = np.asarray(enc.resolutions, dtype=np.int64)
        self.dense = np.asarray(enc.dense_levels, dtype=np.bool_)
        self.size = np.asarray(enc.level_sizes, dtype=np.int64)
        self.off = np.cumsum([0] + list(enc.level_sizes[:-1])).astype(np.int64)


class HashReuseCPU(torch.autograd.Function):
    """Identity on an encoding already computed (without grad) for positions x; backward = the table's
    gradient, as HashEncodeCPU. Lets training reuse the encoding of its density-only first pass."""

    @staticmethod
    def forward(ctx, encoded, x, table, enc):
        ctx.save_for_backward(x)
        ctx.enc = enc
        return encoded.clone() if encoded.requires_grad else encoded

    @staticmethod
    def backward(ctx, grad_out):
        g_x, g = _encoding_backward(ctx, grad_out, ctx.needs_input_grad[1])
        return None, g_x, g, None


class HashEncodeCPU(torch.autograd.Function):
    """Fused hash encoding on CPU: gradients flow to the table, and to the positions when they require
    them (camera pose refinement)."""

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
        g_x, g = _encoding_backward(ctx, grad_out, ctx.needs_input_grad[0])
        return g_x, g, None


def _encoding_backward(ctx, grad_out, positions_need_grad: bool):
    """(gradient of the positions or None, of the table or None) for HashEncodeCPU and HashReuseCPU."""
    (x,) = ctx.saved_tensors
    enc = ctx.enc
    arrs = enc._kernel_arrays
    grad_table = enc.grad_buffer()
    grad_out = grad_out.contiguous()
    # The positions' gradient reads the table as the forward did: before the table's own gradient is applied.
    grad_x = positions_grad(x, grad_out, enc) if positions_need_grad else None
    _hash_backward(
        x.detach().contiguous().numpy(),
        grad_out.numpy(),
        arrs.res,
        arrs.dense,
        arrs.size,
        arrs.off,
        grad_table.numpy(),
        enc.touched_rows(),
    )
    # In fused-grad mode the gradient stays in the encoding's buffer for the lazy Adam.
    return grad_x, (None if enc.fused_grad else grad_table)


if backend.HAVE_NUMBA:

    @njit(parallel=True, cache=True, fastmath=FAST)
    def _sh_forward(d, degree, out):
        for n in prange(d.shape[0]):
            x, y, z = d[n, 0], d[n, 1], d[n, 2]
            out[n, 0] = 0.28209479177387814
            if degree > 1:
                out[n, 1] = -0.48860251190291987 * y
                out[n, 2] = 0.48860251190291987 * z
                out[n, 3] = -0.48860251190291987 * x
            if degree > 2:
                xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
                out[n, 4] = 1.0925484305920792 * xy
                out[n, 5] = -1.0925484305920792 * yz
                out[n, 6] = 0.94617469575755997 * zz - 0.31539156525251999
                out[n, 7] = -1.0925484305920792 * xz
                out[n, 8] = 0.54627421529603959 * xx - 0.54627421529603959 * yy
                if degree > 3:
                    out[n, 9] = 0.59004358992664352 * y * (-3.0 * xx + yy)
                    out[n, 10] = 2.8906114426405538 * xy * z
                    out[n, 11] = 0.45704579946446572 * y * (1.0 - 5.0 * zz)
                    out[n, 12] = 0.3731763325901154 * z * (5.0 * zz - 3.0)
                    out[n, 13] = 0.45704579946446572 * x * (1.0 - 5.0 * zz)
                    out[n, 14] = 1.4453057213202769 * z * (xx - yy)
                    out[n, 15] = 0.59004358992664352 * x * (-xx + 3.0 * yy)


def sh_forward(d: torch.Tensor, degree: int) -> torch.Tensor:
    """encoding.sh_encode in one pass over the directions (the torch version makes ~30 temporaries)."""
    dn = d.detach().contiguous().numpy()
    out = np.empty((dn.shape[0], degree * degree), dtype=dn.dtype)
    _sh_forward(dn, degree, out)
    return torch.from_numpy(out)
