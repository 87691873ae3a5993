"""`extract`: the filtered surface mesh of a NeRF's density, as a PLY with vertex colours.

python -m blender_nerf_deform.engine extract --nerf CKPT --out MESH.ply
    [--threshold T] [--resolution R] [--min-volume V] [--decimate FACES]
    [--region REGION.json [--region ...]] [--pick X Y Z] [--device D]
"""

from __future__ import annotations

import numpy as np

from ..errors import EngineError
from ..files import check_writable
from ..geometry.extract import check_extract_options, extract_nerf_mesh, extract_nerf_regions
from ..geometry.mesh_io import write_ply
from ..geometry.region import check_region_in_box, load_region
from ..nerf.checkpoint import load_nerf


def main(args) -> int:
    # Before minutes of sampling: the options, the region, then the destination.
    check_extract_options(args.resolution, args.threshold, args.min_volume, args.decimate)
    regions = [load_region(path) for path in args.region or []]
    if args.pick is not None and not np.isfinite(args.pick).all():
        raise EngineError(f"--pick must be a finite point, got {args.pick}")
    check_writable(args.out)
    nerf = load_nerf(args.nerf, device=args.device or "auto")
    box = nerf.aabb.detach().cpu().double().numpy().reshape(2, 3)
    for path, region in zip(args.region or [], regions):
        try:
            check_region_in_box(region, box)
        except EngineError as error:
            raise EngineError(f"--region {path}: {error}") from None
    options = {
        "resolution": args.resolution,
        "threshold": args.threshold,
        "min_volume": args.min_volume,
        "decimate": args.decimate,
        "progress": True,
    }
    if regions:
        res = extract_nerf_regions(nerf, regions, pick=args.pick, **options)
    else:
        res = extract_nerf_mesh(nerf, pick=args.pick, **options)
    write_ply(args.out, res.vertices, res.faces, res.colors, cut=res.cut, part=res.part)
    print(res.report())
    t = res.timings
    print(
        f"grid {t['grid_s']:.1f}s, marching cubes {t['marching_cubes_s']:.1f}s, filter {t['filter_s']:.1f}s "
        f"-> {args.out}"
    )
    return 0
