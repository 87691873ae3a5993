"""`bake-volume`: the NeRF, at rest or as posed, sampled on a voxel grid: DIR/<name>.npz per pose.

    python -m blender_nerf_deform.engine bake-volume --nerf CKPT --out DIR
        [--cage CAGE.npz --deformed V.npy|POSES_DIR] [--region REGION.json | --extent nerf|cage]
        [--resolution R] [--supersample S] [--device D]

<name> is the pose file's name without extension (`rest` without a cage).
Each .npz (bend/volume.py: `shape`, `index_to_nerf`, and the voxels that hold
anything: `index`, `density` per NeRF unit, `color` sRGB) is baked into a
temporary file; the files take their place together once every pose is baked
(files.StagedFiles): a run that fails or is interrupted leaves DIR as it was,
without the folders it made. Only earlier bakes are replaced: a file of another
kind, or a folder, where a volume goes is an error before any work. The engine
has no OpenVDB: `tools/vdb_from_npz.py` (run by Blender, or by Python with the bpy
module) turns them into .vdb files, as the add-on's Bake Volume does. Every pose
is checked, and each grid and its memory, before the first bake.
"""

from __future__ import annotations

from pathlib import Path

from ..bend.baked_volume import check_resolution, check_volume_memory, is_baked_volume_file, volume_grid
from ..bend.posed import PosedRenderer
from ..bend.volume import bake_box
from ..errors import EngineError
from ..files import StagedFiles, check_writable
from ..geometry.mesh_io import load_cage
from ..geometry.poses import load_poses, pose_files
from ..geometry.region import load_region
from ..nerf.checkpoint import load_nerf


def check_replaceable(path: Path) -> None:
    """EngineError unless `path` is free or holds an earlier bake (nothing else is replaced)."""
    if path.is_dir():
        raise EngineError(f"cannot write {path}: it is a folder; move it, or bake into another --out")
    if path.exists() and not path.is_file():
        raise EngineError(
            f"cannot write {path}: it is not a file (a pipe, a socket or a device): it is left alone; "
            "move it, or bake into another --out"
        )
    if path.exists() and not is_baked_volume_file(path):
        raise EngineError(
            f"{path} exists and is not a baked volume: it is left alone; move it, or bake into another --out"
        )


def main(args) -> int:
    if (args.cage is None) != (args.deformed is None):
        raise EngineError("--cage and --deformed go together: give both or neither")
    if args.region is not None and args.extent is not None:
        raise EngineError("--region and --extent both say what to bake: give one")
    check_resolution(args.resolution)
    extent = load_region(args.region) if args.region is not None else (args.extent or "nerf")
    out = Path(args.out)
    check_writable(out, folder=True)
    cage, poses, names = None, [None], ["rest"]
    if args.cage is not None:
        cage = load_cage(args.cage)
        files = pose_files(args.deformed)
        poses = load_poses(cage["vertices"], args.deformed, len(files), tets=cage["tets"])
        names = [f.stem for f in files]
    elif extent == "cage":
        raise EngineError("--extent cage needs --cage and --deformed (the cage as posed)")
    targets = [out / f"{name}.npz" for name in names]
    for target in targets:
        check_replaceable(target)
    model = load_nerf(args.nerf, device=args.device or "auto")
    bounds = model.aabb.detach().cpu().double().reshape(2, 3).numpy()
    grids = [volume_grid(bake_box(extent, model, pose), args.resolution, content=bounds) for pose in poses]
    for grid in grids:
        check_volume_memory(grid)
    renderer = PosedRenderer(model, cage["vertices"], cage["tets"]) if cage is not None else PosedRenderer(model)
    from tqdm import tqdm

    with StagedFiles() as staged:
        if not out.is_dir():
            staged.make_folder(out)
        bar = tqdm(list(zip(names, poses, grids, targets)), unit="pose", dynamic_ncols=True)
        for name, pose, grid, target in bar:
            baked, inversion = renderer.bake(grid, pose, supersample=args.supersample)
            if inversion is not None:
                bar.write(f"{name}: {inversion.summary()}")
            nx, ny, nz = grid.shape
            bar.write(
                f"{name}: {nx}x{ny}x{nz} voxels, {baked.stats['active_voxels']} hold anything, "
                f"{baked.stats['seconds']:.1f} s"
            )
            staged.write(target, baked.write)
        staged.commit()
    print(f"wrote {len(poses)} volume{'s' if len(poses) > 1 else ''} to {out}")
    return 0
