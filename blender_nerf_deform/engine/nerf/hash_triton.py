"""The hash encoding of all levels in one Triton kernel, forward and backward (the device path).

Why hand-written: the torch formulation (`HashEncoding.torch_forward`) is a dozen kernels forward (indices,
weights, hashes, one embedding_bag) and as many backward, each reading and writing (N, L, 8) intermediates;
here one kernel reads the points and the table rows and writes the encoding, and one kernel scatters the
gradient into the table (atomic adds), as tiny-cuda-nn's grid encoding does. The same arithmetic as
`HashEncoding.indices_and_weights` (float32 positions and weights, int64 hashes), so it agrees with the torch
path to float rounding; the tests run it under Triton's interpreter (TRITON_INTERPRET=1) on CPU tensors.

Only imported where `backend.use_triton` says Triton runs (CUDA, or the interpreter), so that `triton.jit`
sees the interpreter switch when it decorates the kernels.
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl

from ..launch_count import kernel_launch

# Points per program. The interpreter pays per operation, not per element: far larger blocks there.
BLOCK = 4096 if os.environ.get("TRITON_INTERPRET", "0") == "1" else 128


@triton.jit
def _cell(x_ptr, rows, valid, res, axis: tl.constexpr):
    """Cell index (int64) and fraction of each point along one axis at resolution `res`."""
    x = tl.load(x_ptr + rows * 3 + axis, mask=valid, other=0.0)
    x = tl.where(x == x, x, 0.0)  # NaN counts as 0, as in the CPU kernels
    x = tl.minimum(tl.maximum(x, 0.0), 1.0)
    pos = x * res
    base = tl.floor(pos)
    return base.to(tl.int64), pos - base


@triton.jit
def _corner_row(ix, iy, iz, c: tl.constexpr, r_int, dense: tl.constexpr, table_mask, offset):
    cx = ix + (c & 1)
    cy = iy + ((c >> 1) & 1)
    cz = iz + ((c >> 2) & 1)
    if dense:
        cx = tl.minimum(cx, r_int)
        cy = tl.minimum(cy, r_int)
        cz = tl.minimum(cz, r_int)
        row = cx + cy * (r_int + 1) + cz * (r_int + 1) * (r_int + 1)
    else:
        row = (cx * 1 ^ cy * 2654435761 ^ cz * 805459861) & table_mask
    return row + offset


@triton.jit
def _corner_weight(fx, fy, fz, c: tl.constexpr):
    wx = fx if (c & 1) else 1.0 - fx
    wy = fy if ((c >> 1) & 1) else 1.0 - fy
    wz = fz if ((c >> 2) & 1) else 1.0 - fz
    return wx * wy * wz


@triton.jit
def _level_cells(x_ptr, rows, valid, res_ptr, offset_ptr, lvl):
    """A level's integer resolution, table offset, and each point's cell and fraction along x, y, z."""
    res = tl.load(res_ptr + lvl)
    offset = tl.load(offset_ptr + lvl)
    ix, fx = _cell(x_ptr, rows, valid, res, 0)
    iy, fy = _cell(x_ptr, rows, valid, res, 1)
    iz, fz = _cell(x_ptr, rows, valid, res, 2)
    return res.to(tl.int64), offset, ix, fx, iy, fy, iz, fz


@triton.jit
def _hash_forward(
    x_ptr,
    table_ptr,
    out_ptr,
    res_ptr,
    offset_ptr,
    n,
    table_mask,
    N_LEVELS: tl.constexpr,
    N_DENSE: tl.constexpr,
    F: tl.constexpr,
    BLOCK: tl.constexpr,
):
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = rows < n
    feats = tl.arange(0, F)
    for lvl in tl.static_range(N_LEVELS):
        r_int, offset, ix, fx, iy, fy, iz, fz = _level_cells(x_ptr, rows, valid, res_ptr, offset_ptr, lvl)
        acc = tl.zeros((BLOCK, F), dtype=tl.float32)
        for c in tl.static_range(8):
            row = _corner_row(ix, iy, iz, c, r_int, lvl < N_DENSE, table_mask, offset)
            w = _corner_weight(fx, fy, fz, c)
            v = tl.load(table_ptr + row[:, None] * F + feats[None, :], mask=valid[:, None], other=0.0)
            acc += w[:, None] * v
        tl.store(out_ptr + rows[:, None] * (N_LEVELS * F) + lvl * F + feats[None, :], acc, mask=valid[:, None])


@triton.jit
def _hash_backward(
    x_ptr,
    grad_ptr,
    table_grad_ptr,
    res_ptr,
    offset_ptr,
    n,
    table_mask,
    N_LEVELS: tl.constexpr,
    N_DENSE: tl.constexpr,
    F: tl.constexpr,
    BLOCK: tl.constexpr,
):
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = rows < n
    feats = tl.arange(0, F)
    for lvl in tl.static_range(N_LEVELS):
        r_int, offset, ix, fx, iy, fy, iz, fz = _level_cells(x_ptr, rows, valid, res_ptr, offset_ptr, lvl)
        g = tl.load(
            grad_ptr + rows[:, None] * (N_LEVELS * F) + lvl * F + feats[None, :], mask=valid[:, None], other=0.0
        )
        for c in tl.static_range(8):
            row = _corner_row(ix, iy, iz, c, r_int, lvl < N_DENSE, table_mask, offset)
            w = _corner_weight(fx, fy, fz, c)
            tl.atomic_add(table_grad_ptr + row[:, None] * F + feats[None, :], w[:, None] * g, mask=valid[:, None])


def _launch(kernel, name, n, *args, enc):
    grid = (triton.cdiv(n, BLOCK),)
    with kernel_launch(name):
        kernel[grid](
            *args, n, enc.table_size - 1, N_LEVELS=enc.n_levels, N_DENSE=enc.n_dense, F=enc.n_features, BLOCK=BLOCK
        )


def encode(x: torch.Tensor, table: torch.Tensor, enc) -> torch.Tensor:
    """The encoding (N, L*F) of points x (N, 3) in [0, 1]^3, without autograd."""
    n = x.shape[0]
    out = torch.empty((n, enc.n_levels * enc.n_features), dtype=table.dtype, device=x.device)
    if n:
        _launch(_hash_forward, "hash_forward", n, x, table, out, enc.res_f, enc.offsets, enc=enc)
    return out


def table_gradient(x: torch.Tensor, grad: torch.Tensor, table: torch.Tensor, enc) -> torch.Tensor:
    """The gradient of the table given the encoding's gradient `grad` (N, L*F) at points x."""
    table_grad = torch.zeros_like(table)
    if x.shape[0]:
        _launch(
            _hash_backward,
            "hash_backward",
            x.shape[0],
            x,
            grad.contiguous(),
            table_grad,
            enc.res_f,
            enc.offsets,
            enc=enc,
        )
    return table_grad


class HashEncode(torch.autograd.Function):
    """The encoding, differentiable in the table (positions carry no gradient here: the torch path has it)."""

    @staticmethod
    def forward(ctx, x, table, enc):
        x = x.contiguous()
        ctx.save_for_backward(x)
        ctx.enc = enc
        return encode(x, table, enc)

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return None, table_gradient(x, grad, ctx.enc.table.detach(), ctx.enc), None


class HashReuse(torch.autograd.Function):
    """`encoded` (computed without gradients) as the encoding of x: only the backward runs."""

    @staticmethod
    def forward(ctx, encoded, x, table, enc):
        ctx.save_for_backward(x.contiguous())
        ctx.enc = enc
        return encoded

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return None, None, table_gradient(x, grad, ctx.enc.table.detach(), ctx.enc), None
