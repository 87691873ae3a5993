"""The spherical-harmonics encoding of view directions in one Triton kernel (the device path).

Why hand-written: the torch formulation (`encoding.sh_encode`) is some forty small kernels, one per product
and constant, in every render round and training step; this kernel reads each direction once and writes
its degree^2 values, with the same float32 operations in the same order (on CUDA the compiler may fuse a
multiply and an add: a rounding apart). Directions that carry a gradient (camera pose refinement) stay on
the torch formulation.

Only imported where `backend.use_triton` says Triton runs (CUDA, or the interpreter).
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl

from ..launch_count import kernel_launch

# Directions per program; the interpreter pays per operation, not per element: far larger blocks there.
BLOCK = 4096 if os.environ.get("TRITON_INTERPRET", "0") == "1" else 256


@triton.jit
def _sh(d_ptr, out_ptr, n, DEGREE: tl.constexpr, BLOCK: tl.constexpr):
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = rows < n
    x = tl.load(d_ptr + rows * 3, mask=valid, other=0.0)
    y = tl.load(d_ptr + rows * 3 + 1, mask=valid, other=0.0)
    z = tl.load(d_ptr + rows * 3 + 2, mask=valid, other=0.0)
    base = out_ptr + rows * (DEGREE * DEGREE)
    tl.store(base, tl.zeros_like(x) + 0.28209479177387814, mask=valid)
    if DEGREE > 1:
        tl.store(base + 1, -0.48860251190291987 * y, mask=valid)
        tl.store(base + 2, 0.48860251190291987 * z, mask=valid)
        tl.store(base + 3, -0.48860251190291987 * x, mask=valid)
    if DEGREE > 2:
        xx = x * x
        yy = y * y
        zz = z * z
        xy = x * y
        yz = y * z
        xz = x * z
        tl.store(base + 4, 1.0925484305920792 * xy, mask=valid)
        tl.store(base + 5, -1.0925484305920792 * yz, mask=valid)
        tl.store(base + 6, 0.94617469575755997 * zz - 0.31539156525251999, mask=valid)
        tl.store(base + 7, -1.0925484305920792 * xz, mask=valid)
        tl.store(base + 8, 0.54627421529603959 * xx - 0.54627421529603959 * yy, mask=valid)
        if DEGREE > 3:
            tl.store(base + 9, 0.59004358992664352 * y * (-3.0 * xx + yy), mask=valid)
            tl.store(base + 10, 2.8906114426405538 * xy * z, mask=valid)
            tl.store(base + 11, 0.45704579946446572 * y * (1.0 - 5.0 * zz), mask=valid)
            tl.store(base + 12, 0.3731763325901154 * z * (5.0 * zz - 3.0), mask=valid)
            tl.store(base + 13, 0.45704579946446572 * x * (1.0 - 5.0 * zz), mask=valid)
            tl.store(base + 14, 1.4453057213202769 * z * (xx - yy), mask=valid)
            tl.store(base + 15, 0.59004358992664352 * x * (-xx + 3.0 * yy), mask=valid)


def sh_encode(d: torch.Tensor, degree: int) -> torch.Tensor:
    """Real spherical harmonics (N, degree^2) of unit directions d (N, 3) float32, degree 1..4."""
    n = d.shape[0]
    out = torch.empty((n, degree * degree), dtype=torch.float32, device=d.device)
    if n:
        with kernel_launch("sh_encode"):
            _sh[(triton.cdiv(n, BLOCK),)](d.contiguous(), out, n, DEGREE=degree, BLOCK=BLOCK)
    return out
