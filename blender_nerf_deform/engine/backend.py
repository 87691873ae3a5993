"""The one place that decides which code path runs: numba kernels on CPU, torch everywhere else.

Every stage with fused CPU kernels (hash encoding, ray marching, lazy Adam,
point location, ray bending, ARAP) asks `use_kernels(device)` here instead of
deciding for itself, so a single switch moves the whole engine between the
two paths:

- numba missing (it is optional at run time): torch on every device;
- `NERF_DEFORM_KERNELS=torch` in the environment, or `forced("torch")` in a
  test or benchmark: the torch path on CPU too (the code CUDA runs);
- otherwise numba's kernels for CPU tensors and torch for CUDA ones.

Importing this module imports neither numba nor torch.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os

HAVE_NUMBA = importlib.util.find_spec("numba") is not None
PATHS = ("auto", "torch")
_path = os.environ.get("NERF_DEFORM_KERNELS", "auto").strip().lower() or "auto"
if _path not in PATHS:
    raise SystemExit(f"NERF_DEFORM_KERNELS must be one of {', '.join(PATHS)}, got {_path!r}")


def use_kernels(device="cpu") -> bool:
    """Whether work on `device` (a torch.device or its name) runs the numba kernels."""
    kind = getattr(device, "type", None) or str(device).split(":")[0]
    return HAVE_NUMBA and _path == "auto" and kind == "cpu"


def path() -> str:
    """"numba" or "torch": what CPU work runs now."""
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
