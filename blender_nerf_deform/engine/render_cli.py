"""`render` command: render the cameras of a transforms.json to DIR/<name>.png (RGBA, straight alpha).

    python -m blender_nerf_deform.engine render --nerf CKPT --cameras transforms.json --out DIR
        [--cage CAGE.npz --deformed V.npy|POSES_DIR] [--downscale K] [--device D]

<name> is the basename of the frame's file_path without extension. Only the
cameras are read (images need not exist when `w` and `h` are given). Each PNG
is written to a temporary file and renamed.

With --cage/--deformed every frame is ray-bent through the cage (engine/bending.py):

- `--deformed V.npy`: one (N,3) pose for every frame;
- `--deformed POSES_DIR`: an animation. The folder's `*.npy` files, in natural
  name order (digit runs compare as numbers, so `pose_2` comes before
  `pose_10`), are the poses of the frames of transforms.json in file order:
  the k-th array poses the k-th frame. For a still camera, repeat its frame in
  transforms.json with one file_path per frame. The counts must match.

Every pose is read and checked (shape, vertex count, finite) before the first
frame is rendered, so a bad file stops the run with nothing half-done. The
cage's `CageBend` is built once (its rest-cage locator) and posed per frame.
Each bent frame prints how many tets its pose inverts or flattens.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .checkpoint import load_nerf
from .dataset import load_dataset
from .errors import EngineError
from .files import atomic_write
from .renderer import render_image


def _natural_key(path: Path):
    return [(0, int(part), part) if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", path.name)]


def pose_files(deformed_path) -> list[Path]:
    """The pose file(s) named by --deformed: [V.npy], or a folder's *.npy in natural name order."""
    path = Path(deformed_path)
    if path.is_dir():
        files = sorted((p for p in path.glob("*.npy") if p.is_file()), key=_natural_key)
        if not files:
            raise EngineError(f"--deformed {path}: the folder holds no .npy pose files")
        return files
    if not path.exists():
        raise EngineError(f"deformed vertices {path} do not exist")
    return [path]


def load_pose(path, vertex_shape: tuple) -> np.ndarray:
    """One (N,3) pose of the cage's N vertices, checked; errors name the file."""
    try:
        deformed = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise EngineError(f"deformed vertices {path} do not exist") from None
    except (ValueError, OSError) as exc:
        raise EngineError(f"cannot read deformed vertices {path}: {exc}") from None
    if not isinstance(deformed, np.ndarray) or deformed.ndim != 2 or deformed.shape[1] != 3 \
            or not np.issubdtype(deformed.dtype, np.number):
        shape = getattr(deformed, "shape", None)
        raise EngineError(f"{path}: deformed vertices must be a finite {vertex_shape} array, the cage's shape "
                          f"(same vertices, same order), got {shape}")
    if deformed.shape != vertex_shape:
        raise EngineError(f"{path}: deformed vertices must be a finite {vertex_shape} array, the cage's shape "
                          f"(same vertices, same order), got {deformed.shape}: {deformed.shape[0]} vertices, "
                          f"the cage has {vertex_shape[0]}")
    bad = np.flatnonzero(~np.isfinite(deformed).all(axis=1))
    if len(bad):
        raise EngineError(f"{path}: deformed vertices must be a finite {vertex_shape} array, but {len(bad)} of its "
                          f"rows hold NaN or inf (first: vertex {bad[0]})")
    return deformed.astype(np.float64)


def load_poses(cage_vertices: np.ndarray, deformed_path, n_frames: int) -> list[np.ndarray]:
    """One checked pose per frame: a single file repeated, or a folder's files matched to frames in order."""
    files = pose_files(deformed_path)
    if Path(deformed_path).is_dir() and len(files) != n_frames:
        raise EngineError(f"--deformed {deformed_path}: {len(files)} pose files (.npy) for {n_frames} camera frames "
                          "in --cameras; give one pose per frame")
    poses = [load_pose(f, cage_vertices.shape) for f in files]
    return poses if len(poses) == n_frames else poses * n_frames


def write_png_rgba(path, rgba: np.ndarray) -> None:
    """Write an (H, W, 4) float straight-alpha image as an 8-bit RGBA PNG, atomically."""
    from PIL import Image

    arr = (np.clip(rgba, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    atomic_write(path, lambda f: Image.fromarray(arr, mode="RGBA").save(f, format="PNG"))


def main(args) -> int:
    if (args.cage is None) != (args.deformed is None):
        raise EngineError("--cage and --deformed go together: give both or neither")
    cams = load_dataset(args.cameras, downscale=getattr(args, "downscale", 1) or 1, load_images=False)
    names = [c.name for c in cams.cameras]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})[0]
        raise EngineError(f"{cams.source}: two frames are both named {dup!r}; their PNGs would overwrite each other")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise EngineError(f"--out {out}: exists and is not a folder")
    poses, cage = None, None
    if args.cage is not None:
        from .mesh_io import load_cage

        cage = load_cage(args.cage)
        poses = load_poses(cage["vertices"], args.deformed, len(cams.cameras))
    model = load_nerf(args.nerf, device=getattr(args, "device", "auto") or "auto")
    bend = None
    if cage is not None:
        from .bending import CageBend

        bend = CageBend(model, cage["vertices"], cage["tets"])
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    bar = tqdm(cams.cameras, unit="frame", dynamic_ncols=True)
    last_pose = None
    for k, cam in enumerate(bar):
        extra = {}
        if bend is not None:
            if poses[k] is not last_pose:  # a single V.npy is posed once for all frames
                bend.set_deformed(poses[k])
                last_pose = poses[k]
            extra = {"sample_transform": bend.sample_transform, "occupancy": bend.occupancy}
            bar.write(f"frame {cam.name}: {bend.inversion.summary()}")
        result = render_image(model, cam, **extra)
        write_png_rgba(out / f"{cam.name}.png", result["rgba"])
    print(f"wrote {len(cams)} frames to {out}")
    return 0
