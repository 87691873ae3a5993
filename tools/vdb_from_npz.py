#!/usr/bin/env python3
"""Turn `bake-volume`'s .npz files into OpenVDB files, with the OpenVDB module Blender ships.

    blender -b --python tools/vdb_from_npz.py -- IN.npz|IN_DIR OUT_DIR [--scale S]
    .venv/bin/python tools/vdb_from_npz.py IN.npz|IN_DIR OUT_DIR [--scale S]     # Python with the bpy module

The engine has no OpenVDB; this writes each baked frame as the add-on's Bake Volume does
(addon/export/volume_file.py): grids `density` (per unit length: the NeRF's density divided by
--scale, the world units per NeRF unit of where the volume will sit; default 1) and `color`
(scene-linear: the NeRF's sRGB decoded), the grids' transform from the voxel indices to the
NeRF's frame. OUT_DIR/<name>.vdb per IN file; every input is read and checked before the first
file is written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(prog="vdb_from_npz.py", description=__doc__.split("\n\n")[0])
    p.add_argument("source", type=Path, help="a baked .npz, or a folder of them")
    p.add_argument("out", type=Path, help="folder for the .vdb files")
    p.add_argument("--scale", type=float, default=1.0, help="world units per NeRF unit (default 1)")
    args = p.parse_args(argv)

    import numpy as np

    from blender_nerf_deform.addon.data.images import srgb_to_linear
    from blender_nerf_deform.addon.export.volume_file import VolumeFileError, write_vdb
    from blender_nerf_deform.engine.bend.baked_volume import load_baked
    from blender_nerf_deform.engine.errors import EngineError

    files = sorted(args.source.glob("*.npz")) if args.source.is_dir() else [args.source]
    if not files:
        print(f"error: {args.source} holds no .npz files", file=sys.stderr)
        return 2
    if not (args.scale > 0 and np.isfinite(args.scale)):
        print(f"error: --scale must be a positive number, got {args.scale}", file=sys.stderr)
        return 2
    try:
        baked = [load_baked(f) for f in files]
        args.out.mkdir(parents=True, exist_ok=True)
        for f, b in zip(files, baked):
            write_vdb(args.out / f"{f.stem}.vdb", b.grid.shape, b.grid.index_to_nerf, b.index, b.density / args.scale,
                      srgb_to_linear(np.clip(b.color, 0.0, 1.0)))
            print(f"{f} -> {args.out / (f.stem + '.vdb')}: {len(b.index)} voxels")
    except (EngineError, VolumeFileError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
