"""The one place that decides which code path runs: numba kernels on CPU, torch everywhere else.

Every stage with fused CPU kernels (hash encoding, ray marching, lazy Adam,
point location, ray bending, ARAP) asks `use_kernels(device)` here instead of
deciding for itself, so a single switch moves the whole engine between the
two paths:

- numba missing (it is optional at run time): torch on every device;
- `NERF_DEFORM_KERNELS=torch` in the environment, or `forced("torch")` in a
  test or benchmark: the torch path on CPU too (the code CUDA runs);
- otherwise numba's kernels for CPU tensors and torch for CUDA ones.

On the torch path, the hottest pieces run as Triton kernels where Triton can run them (`use_triton`): on
CUDA, and on CPU tensors under Triton's interpreter (TRITON_INTERPRET=1, how the tests run them).
`NERF_DEFORM_TRITON=0` or `triton_enabled(False)` keeps the torch formulation (to compare with).

Importing this module imports neither numba nor torch nor triton.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os

HAVE_NUMBA = importlib.util.find_spec("numba") is not None
HAVE_TRITON = importlib.util.find_spec("triton") is not None
_triton = os.environ.get("NERF_DEFORM_TRITON", "1").strip() != "0"
PATHS = ("auto", "torch")
_path = os.environ.get("NERF_DEFORM_KERNELS", "auto").strip().lower() or "auto"
if _path not in PATHS:
    raise SystemExit(f"NERF_DEFORM_KERNELS must be one of {', '.join(PATHS)}, got {_path!r}")


def use_kernels(device="cpu") -> bool:
    """Whether work on `device` (a torch.device or its name) runs the numba kernels."""
    kind = getattr(device, "type", None) or str(device).split(":")[0]
    return HAVE_NUMBA and _path == "auto" and kind == "cpu"


def path() -> str:
    """ "numba" or "torch": what CPU work runs now."""
    return "numba" if use_kernels("cpu") else "torch"


@contextlib.contextmanager
def forced(name: str):
    """Run the block on one code path: "torch" (what CUDA runs, on any device) or "auto"."""
    global _path
    if name not in PATHS:
        raise ValueError(f"code path must be one of {PATHS}, got {name!r}")
    previous, _path = _path, name
    try:
        yield
    finally:
        _path = previous


def use_triton(device="cpu") -> bool:
    """Whether torch-path work on `device` runs the Triton kernels: on CUDA, and on the CPU only under Triton's
    interpreter (TRITON_INTERPRET=1 when the kernels are first imported)."""
    if not (HAVE_TRITON and _triton) or use_kernels(device):
        return False
    kind = getattr(device, "type", None) or str(device).split(":")[0]
    return kind == "cuda" or (kind == "cpu" and os.environ.get("TRITON_INTERPRET", "0") == "1")


@contextlib.contextmanager
def triton_enabled(flag: bool):
    """Run the block with the Triton kernels (True, where they can run) or with the torch formulation."""
    global _triton
    previous, _triton = _triton, bool(flag)
    try:
        yield
    finally:
        _triton = previous
