#!/usr/bin/env python3
"""Turn `bake-volume`'s .npz files into OpenVDB files, with the OpenVDB module Blender ships.

    blender -b --python tools/vdb_from_npz.py -- IN.npz|IN_DIR OUT_DIR [--scale S]
    .venv/bin/python tools/vdb_from_npz.py IN.npz|IN_DIR OUT_DIR [--scale S]     # Python with the bpy module

The engine has no OpenVDB; this writes each baked frame as the add-on's Bake Volume does
(addon/export/volume_file.py): grids `density` (per unit length: the NeRF's density divided by
--scale, the world units per NeRF unit of where the volume will sit; default 1) and `color`
(scene-linear: the NeRF's sRGB decoded), the grids' transform from the voxel indices to the
NeRF's frame. OUT_DIR/<name>.vdb per IN file. Every input is read and checked (its arrays' types,
shapes, values and memory) before the first file is written; the files take their place together
at the end (a run that fails leaves OUT_DIR as it was), and only OpenVDB files are replaced.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(prog="vdb_from_npz.py", description=__doc__.split("\n\n")[0])
    p.add_argument("source", type=Path, help="a baked .npz, or a folder of them")
    p.add_argument("out", type=Path, help="folder for the .vdb files")
    p.add_argument("--scale", type=float, default=1.0, help="world units per NeRF unit (default 1)")
    args = p.parse_args(argv)

    from blender_nerf_deform.engine.errors import run_command

    return run_command("vdb_from_npz.py", lambda: convert(args.source, args.out, args.scale))


def convert(source: Path, out: Path, scale: float) -> None:
    import numpy as np

    from blender_nerf_deform.addon.data.images import srgb_to_linear
    from blender_nerf_deform.addon.export.volume_file import (
        VolumeFileError,
        check_vdb_replaceable,
        scaled_density,
        write_vdb,
    )
    from blender_nerf_deform.engine.bend.baked_volume import load_baked
    from blender_nerf_deform.engine.errors import EngineError
    from blender_nerf_deform.engine.files import StagedFiles, check_writable

    if not (math.isfinite(scale) and scale > 0):
        raise EngineError(f"--scale must be a positive number, got {scale}")
    if not source.exists():
        raise EngineError(f"{source} does not exist")
    files = sorted(f for f in source.glob("*.npz") if f.is_file()) if source.is_dir() else [source]
    if not files:
        raise EngineError(f"{source} holds no .npz files")
    if out.exists() and not out.is_dir():  # (check_writable's message names an --out this tool does not have)
        raise EngineError(f"OUT_DIR {out} exists and is not a folder: give a folder for the .vdb files")
    check_writable(out, folder=True)
    targets = [out / f"{f.stem}.vdb" for f in files]
    try:
        for target in targets:
            check_vdb_replaceable(target)
        baked = [load_baked(f) for f in files]
        with StagedFiles() as staged:
            if not out.is_dir():
                staged.make_folder(out)
            for f, b, target in zip(files, baked, targets):
                write_vdb(
                    staged.temporary(target),
                    b.grid.shape,
                    b.grid.index_to_nerf,
                    b.index,
                    scaled_density(b.density, scale, f"{f}: --scale {scale:g}"),
                    srgb_to_linear(np.clip(b.color, 0.0, 1.0)),
                    where=str(f),
                )
                print(f"{f} -> {target}: {len(b.index)} voxels")
            staged.commit()
    except VolumeFileError as exc:
        raise EngineError(str(exc)) from None


if __name__ == "__main__":
    raise SystemExit(main())
