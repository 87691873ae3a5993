"""numba's cache of the engine's kernels: one entry for every copy of the same engine, stale once a
kernel file of its stage changes. The kernel modules (`*_kernels.py`) take `njit` and `prange` from here.

numba (0.68) files a cached kernel under a hash of its source folder's path and stamps it with the
content of that one file. Two things follow that the engine does not want:

- every copy of the engine compiles the same kernels again (`compile` from nothing takes tens of
  seconds): the repository's command line, the extension installed in each Blender's user folder, a
  test's copy. `make smoke`'s five releases each compiled them; `make demo`'s worker compiled the frame
  kernels its training had just compiled;
- surface_arap_kernels.py inlines functions of arap_kernels.py: a change to arap_kernels.py alone left
  the other's cached kernels in use.

The locators here stamp every kernel with one digest of all the kernel files of its stage (the
folder: nerf, geometry, bend; a kernel module imports no other engine module but the kernel modules
beside it, kernel_cache and backend; test_kernel_cache.py checks it) and, with
NUMBA_CACHE_DIR set (the worker's user folder, the test suite, the demo, the smoke), file it under
NUMBA_CACHE_DIR/<the kernel's package>, e.g. `blender_nerf_deform.engine.nerf`: the same folder for
every copy with that package name. The package name is part of the place because a cached kernel
imports its module by name when it loads. Without NUMBA_CACHE_DIR, kernels stay next to their source
(__pycache__), as numba keeps them. Every other file keeps numba's own locators.

Written against numba's cache locator classes (numba.core.caching; numba is pinned in requirements).
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path

from numba import njit, prange
from numba.core import caching, config

__all__ = ["njit", "prange"]  # the kernels' decorator and parallel loop, with the locators installed

ENGINE_ROOT = Path(__file__).resolve().parent
KERNEL_SUFFIX = "_kernels.py"


def kernel_files() -> list[Path]:
    """The engine's kernel modules (the only ones with cached kernels; test_kernel_cache.py checks it)."""
    return sorted(ENGINE_ROOT.rglob(f"*{KERNEL_SUFFIX}"))


@functools.cache
def kernels_digest(stage: Path) -> str:
    """SHA-256 of the names and contents of the kernel files in the folder `stage`, in one."""
    h = hashlib.sha256()
    for path in sorted(stage.glob(f"*{KERNEL_SUFFIX}")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def _is_kernel_file(py_file: str) -> bool:
    path = Path(py_file).resolve()
    return path.name.endswith(KERNEL_SUFFIX) and ENGINE_ROOT in path.parents


class _KernelFiles:
    """Locator mixin: the engine's kernel files only, each stamped with its stage's digest."""

    def get_source_stamp(self):
        return kernels_digest(Path(self._py_file).resolve().parent)

    @classmethod
    def from_function(cls, py_func, py_file):
        if not _is_kernel_file(py_file):
            return None
        return super().from_function(py_func, py_file)  # numba's: None where it cannot write


class SharedKernelLocator(_KernelFiles, caching.UserProvidedCacheLocator):
    """A kernel under NUMBA_CACHE_DIR/<its package> (none without NUMBA_CACHE_DIR)."""

    def __init__(self, py_func, py_file):
        super().__init__(py_func, py_file)
        package = py_func.__module__.rpartition(".")[0] or "engine"
        self._cache_path = os.path.join(config.CACHE_DIR, package)


class InTreeKernelLocator(_KernelFiles, caching.InTreeCacheLocator):
    """A kernel next to its source, numba's place without NUMBA_CACHE_DIR."""


def install() -> None:
    """Put the engine's locators before numba's own (idempotent)."""
    for cls in (InTreeKernelLocator, SharedKernelLocator):  # Shared ends up first
        if cls not in caching.CacheImpl._locator_classes:
            caching.CacheImpl._locator_classes.insert(0, cls)


install()
