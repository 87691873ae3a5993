"""`render`: render the cameras of a transforms.json to DIR/<name>.png (RGBA, straight alpha).

    python -m blender_nerf_deform.engine render --nerf CKPT --cameras transforms.json --out DIR
        [--cage CAGE.npz --deformed V.npy|POSES_DIR] [--downscale K] [--device D]

<name> is the basename of the frame's file_path without extension. Only the
cameras are read (images need not exist when `w` and `h` are given). Each PNG
is written to a temporary file and renamed. With --cage/--deformed every frame
is ray-bent through the cage (bend/): one pose for all frames (V.npy), or a
folder of poses matched to the frames in natural name order (geometry/poses.py);
every pose is checked before the first frame renders, and each bent frame
prints how many tets its pose inverts or flattens. DIR is checked for writing
before anything loads; a run that fails before its first frame removes the DIR
it created.
"""

from __future__ import annotations

from pathlib import Path

from ..bend.posed import PosedRenderer
from ..errors import EngineError
from ..files import check_writable
from ..geometry.mesh_io import load_cage
from ..geometry.poses import load_poses
from ..nerf.checkpoint import load_nerf
from ..nerf.dataset import load_dataset
from ..png import write_png_rgba
from ..service.requests import CagePose, RestPose


def main(args) -> int:
    if (args.cage is None) != (args.deformed is None):
        raise EngineError("--cage and --deformed go together: give both or neither")
    cams = load_dataset(args.cameras, downscale=args.downscale, load_images=False)
    names = [c.name for c in cams.cameras]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})[0]
        raise EngineError(f"{cams.source}: two frames are both named {dup!r}; their PNGs would overwrite each other")
    out = Path(args.out)
    check_writable(out, folder=True)
    cage, poses = None, [RestPose()] * len(cams.cameras)  # each frame's pose, as the worker's render takes it
    if args.cage is not None:
        cage = load_cage(args.cage)
        poses = [CagePose(v) for v in load_poses(cage["vertices"], args.deformed, len(cams.cameras), tets=cage["tets"])]
    model = load_nerf(args.nerf, device=args.device or "auto")
    renderer = PosedRenderer(model, cage["vertices"], cage["tets"]) if cage is not None else PosedRenderer(model)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    try:
        bar = tqdm(cams.cameras, unit="frame", dynamic_ncols=True)
        for k, cam in enumerate(bar):
            deformed = poses[k].deformed_vertices if isinstance(poses[k], CagePose) else None
            result = renderer.render(cam, deformed, substeps=args.substeps)
            if result["inversion"] is not None:
                bar.write(f"frame {cam.name}: {result['inversion'].summary()}")
            write_png_rgba(out / f"{cam.name}.png", result["rgba"])
    except EngineError:
        if created and not any(out.iterdir()):
            out.rmdir()
        raise
    print(f"wrote {len(cams)} frames to {out}")
    return 0
