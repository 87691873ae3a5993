"""`compile`: compile the CPU kernels into numba's cache, once per machine (and per engine version).

    python -m blender_nerf_deform.engine compile

Without it the first `train` or `render` on a machine compiles every kernel it touches on the way
(several seconds more than from a warm cache). Run it where the time is
expected: after installing (Set Up Worker does), or in a render farm's image build. The cache is
numba's: NUMBA_CACHE_DIR when set (the add-on's worker sets it), else `__pycache__` beside the
sources. Writes nothing else.
"""

from __future__ import annotations

import time

from ..bend import warmup as bend_warmup
from ..geometry import warmup as geometry_warmup
from ..nerf import warmup as nerf_warmup


def main(args) -> int:
    if not nerf_warmup.has_kernels():
        print("nothing to compile: the CPU kernels are off here (no numba, or NERF_DEFORM_KERNELS chose torch)")
        return 0
    t0 = time.perf_counter()
    models = nerf_warmup.compile_kernels()
    print(f"compiled NeRF training and rendering in {time.perf_counter() - t0:.1f} s", flush=True)
    t = time.perf_counter()
    geometry_warmup.compile_kernels()
    print(f"compiled ARAP and point location in {time.perf_counter() - t:.1f} s", flush=True)
    t = time.perf_counter()
    bend_warmup.compile_kernels(models, nerf_warmup.tiny_scene(True).cameras[0])
    print(f"compiled ray bending in {time.perf_counter() - t:.1f} s", flush=True)
    print(f"the kernels are compiled ({time.perf_counter() - t0:.1f} s)")
    return 0
