"""`extract`: the filtered surface mesh of a NeRF's density, as a PLY with vertex colours.

    python -m blender_nerf_deform.engine extract --nerf CKPT --out MESH.ply
        [--threshold T] [--resolution R] [--min-volume V] [--decimate FACES] [--device D]
"""

from __future__ import annotations

from ..files import check_writable
from ..geometry.extract import check_extract_options, extract_nerf_mesh
from ..geometry.mesh_io import write_ply
from ..nerf.checkpoint import load_nerf


def main(args) -> int:
    # Before minutes of sampling: the options, then the destination.
    check_extract_options(args.resolution, args.threshold, args.min_volume, args.decimate)
    check_writable(args.out)
    nerf = load_nerf(args.nerf, device=args.device or "auto")
    res = extract_nerf_mesh(nerf, resolution=args.resolution, threshold=args.threshold, min_volume=args.min_volume,
                            decimate=args.decimate, progress=True)
    write_ply(args.out, res.vertices, res.faces, res.colors)
    print(res.report())
    t = res.timings
    print(f"grid {t['grid_s']:.1f}s, marching cubes {t['marching_cubes_s']:.1f}s, filter {t['filter_s']:.1f}s -> {args.out}")
    return 0
