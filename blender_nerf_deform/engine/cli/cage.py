"""`cage`: the tetrahedral cage around a NeRF's extracted mesh, built once, as CAGE.npz.

    python -m blender_nerf_deform.engine cage --nerf CKPT --mesh MESH.ply --out CAGE.npz
        [--margin M] [--edge-length L] [--target-tets N] [--threshold T]
"""

from __future__ import annotations

from ..files import check_writable
from ..geometry.cage import build_nerf_cage, check_cage_options, vertices_outside
from ..geometry.mesh_io import read_ply, save_cage
from ..nerf.checkpoint import load_nerf


def main(args) -> int:
    check_cage_options(args.margin, args.edge_length, args.target_tets, args.threshold)
    check_writable(args.out)
    verts, faces, _ = read_ply(args.mesh)
    nerf = load_nerf(args.nerf)
    cage = build_nerf_cage(verts, faces, nerf, args.margin, args.threshold,
                           edge_length=args.edge_length, target_tets=args.target_tets, name=f"mesh {args.mesh}")
    aabb = nerf.aabb.detach().cpu().double().numpy().reshape(2, 3)
    save_cage(args.out, cage.vertices, cage.tets, margin=cage.margin, clearance=cage.clearance, bounds=aabb)
    print(
        f"cage: {len(cage.tets)} tets, {len(cage.vertices)} vertices, margin {cage.margin:.4g}, clearance {cage.clearance:.4g}, "
        f"{vertices_outside(cage.vertices, aabb)} vertices outside the NeRF's bounds; envelope {cage.timings['envelope_s']:.1f}s, "
        f"tetrahedralize {cage.timings['tetrahedralize_s']:.1f}s -> {args.out}"
    )
    return 0
