"""`render` command: render the cameras of a transforms.json to DIR/<name>.png (RGBA, straight alpha).

    python -m blender_nerf_deform.engine render --nerf CKPT --cameras transforms.json --out DIR
        [--cage CAGE.npz --deformed V.npy] [--downscale K] [--device D]

<name> is the basename of the frame's file_path without extension. Only the
cameras are read (images need not exist when `w` and `h` are given). Each PNG
is written to a temporary file and renamed.

With --cage/--deformed every frame is ray-bent through the cage posed by V.npy
(engine/bending.py): `bending_transform` returns the renderer's
`sample_transform` and the deformed space's occupancy grid.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .checkpoint import load_nerf
from .dataset import load_dataset
from .errors import EngineError
from .files import atomic_write
from .renderer import render_image


def bending_transform(model, cage_path, deformed_path):
    """(sample_transform, occupancy) for rendering through the cage at `cage_path` posed by `deformed_path`."""
    from .bending import CageBend
    from .mesh_io import load_cage

    cage = load_cage(cage_path)
    try:
        deformed = np.load(deformed_path, allow_pickle=False)
    except FileNotFoundError:
        raise EngineError(f"deformed vertices {deformed_path} do not exist") from None
    except (ValueError, OSError) as exc:
        raise EngineError(f"cannot read deformed vertices {deformed_path}: {exc}") from None
    if deformed.shape != cage["vertices"].shape or not np.isfinite(deformed).all():
        raise EngineError(
            f"{deformed_path}: deformed vertices must be a finite {cage['vertices'].shape} array, the cage's shape "
            f"(same vertices, same order), got {deformed.shape}"
        )
    bend = CageBend(model, cage["vertices"], cage["tets"]).set_deformed(deformed)
    if not bend.inversion.ok:
        print(f"{deformed_path}: {bend.inversion.summary()}")
    return bend.sample_transform, bend.occupancy


def write_png_rgba(path, rgba: np.ndarray) -> None:
    """Write an (H, W, 4) float straight-alpha image as an 8-bit RGBA PNG, atomically."""
    from PIL import Image

    arr = (np.clip(rgba, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    atomic_write(path, lambda f: Image.fromarray(arr, mode="RGBA").save(f, format="PNG"))


def main(args) -> int:
    if (args.cage is None) != (args.deformed is None):
        raise EngineError("--cage and --deformed go together: give both or neither")
    model = load_nerf(args.nerf, device=getattr(args, "device", "auto") or "auto")
    cams = load_dataset(args.cameras, downscale=getattr(args, "downscale", 1) or 1, load_images=False)
    extra = {}
    if args.cage is not None:
        transform, occupancy = bending_transform(model, args.cage, args.deformed)
        extra = {"sample_transform": transform, "occupancy": occupancy}
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise EngineError(f"--out {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    names = [c.name for c in cams.cameras]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})[0]
        raise EngineError(f"{cams.source}: two frames are both named {dup!r}; their PNGs would overwrite each other")
    from tqdm import tqdm

    for cam in tqdm(cams.cameras, unit="frame", dynamic_ncols=True):
        result = render_image(model, cam, **extra)
        write_png_rgba(out / f"{cam.name}.png", result["rgba"])
    print(f"wrote {len(cams)} frames to {out}")
    return 0
