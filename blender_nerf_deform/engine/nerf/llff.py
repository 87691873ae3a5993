"""LLFF captures (Mildenhall et al. 2019): `poses_bounds.npy` and `images/`, `images_N/`.

Read by hand with numpy: the format is one N x 17 array, and no library reads it without
also pulling in its NeRF (nerfstudio, the LLFF repository itself).

`poses_bounds.npy`: row i is a 3x5 matrix [R | t | hwf] (row-major) and the near/far depth
bounds of image i in sorted file order (LLFF pairs them by sorting; file names are free).
R's columns are the camera's axes in world coordinates in LLFF's order [down, right,
backwards]; OpenGL's [right, up, backwards] is [col 1, -col 0, col 2]. hwf is the height,
width and focal length (pixels) of the full-resolution photos; the focal is scaled per axis
to the size of the images read. The principal point is the image centre and the lens a
pinhole, as every LLFF reader takes them.

Images: `downscale=k` reads `images_k/` when there is one; else box-filters the nearest
finer folder (`images/`, or `images_m/` with m dividing k); with k = 1 and no `images/`
(redistributed captures often lack the full-size photos) the finest `images_N/` is used, and
said. The path may also be an image folder itself (then `downscale` filters it further).

Orientation, as `prepare` puts a capture (engine/sfm/orient.py) but with the focus taken from
the bounds, since forward-facing optical axes barely cross: the cameras' mean up becomes +Z;
the origin is the centre of `inner_aabb`; the scale puts the cameras 4 units from it on
average. The boxes (axis-aligned in that frame) come from the view frusta:
- `aabb`: every camera's frustum between its near and far bound: all the scene COLMAP saw;
- `inner_aabb`: the frusta between the near bound and the depth halfway in disparity
  between near and far (2 / (1/near + 1/far)): the nearer half of the scene in the measure
  that LLFF's NDC NeRFs sample uniformly, where a forward-facing capture's subject is; what
  lies beyond is background.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..errors import EngineError
from ..sfm.orient import apply_to_cameras, orientation
from .camera import Camera
from .frames import FrameSource, frame_name, image_size

log = logging.getLogger(__name__)

POSES = "poses_bounds.npy"
_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg"}
_FACTOR = re.compile(r"images(?:_(\d+))?$")
CAMERA_DISTANCE = 4.0


def find(path: Path) -> tuple[Path, Path | None] | None:
    """(capture folder, image folder or None) when `path` is an LLFF capture, its poses file or one
    of its image folders; else None."""
    if path.is_file():
        return (path.parent, None) if path.name == POSES else None
    if (path / POSES).is_file():
        return path, None
    if _FACTOR.match(path.name) and (path.parent / POSES).is_file():
        return path.parent, path
    return None


def _factor(folder: Path) -> int:
    m = _FACTOR.match(folder.name)
    return int(m.group(1) or 1)


def _photos(folder: Path) -> list[Path]:
    return sorted(
        (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES), key=lambda p: p.name
    )


def _choose_folder(root: Path, downscale: int) -> tuple[Path, int]:
    """(image folder, box filter still to apply) for `downscale` (module docstring)."""
    folders = sorted((p for p in root.iterdir() if p.is_dir() and _FACTOR.match(p.name) and _photos(p)), key=_factor)
    if not folders:
        raise EngineError(f"{root}: LLFF capture without images: no images/ or images_N/ folder with photos")
    by_factor = {_factor(p): p for p in folders}
    if downscale in by_factor:
        return by_factor[downscale], 1
    if downscale == 1:
        finest = folders[0]
        log.info("note: %s: no full-resolution images/ folder: reading %s/", root, finest.name)
        return finest, 1
    finer = [m for m in by_factor if m < downscale and downscale % m == 0]
    if not finer:
        raise EngineError(
            f"{root}: no images_{downscale}/ for --downscale {downscale}, nor a finer folder it divides "
            f"(there are: {', '.join(p.name for p in folders)})"
        )
    m = max(finer)
    return by_factor[m], downscale // m


def _frustum_box(
    c2ws: np.ndarray, tan_x: np.ndarray, tan_y: np.ndarray, near: np.ndarray, far: np.ndarray
) -> np.ndarray:
    """Bounding box of every camera's frustum between z-depths near and far (per camera)."""
    corners = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            d = np.stack([sx * tan_x, sy * tan_y, -np.ones_like(tan_x)], -1)  # camera space, z-depth 1
            d = np.einsum("nij,nj->ni", c2ws[:, :3, :3], d)
            for depth in (near, far):
                corners.append(c2ws[:, :3, 3] + d * depth[:, None])
    pts = np.concatenate(corners)
    return np.stack([pts.min(0), pts.max(0)])


def read(path: Path, downscale: int, load_images: bool) -> FrameSource:
    root, folder = find(path)
    poses_file = root / POSES
    try:
        arr = np.load(poses_file, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise EngineError(f"{poses_file}: cannot read ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or len(arr) == 0 or not np.issubdtype(arr.dtype, np.number):
        raise EngineError(
            f"{poses_file}: shape {arr.shape} {arr.dtype}, expected N x 17 numbers (3x5 pose + near, far)"
        )
    arr = arr.astype(np.float64)
    extra = 1
    if folder is None:
        folder, extra = _choose_folder(root, downscale)
    else:
        extra = downscale
    photos = _photos(folder)
    if len(photos) != len(arr):
        raise EngineError(
            f"{folder}: {len(photos)} images for the {len(arr)} rows of {poses_file} (LLFF pairs them "
            "in sorted name order, so none may be missing or extra)"
        )
    for i, row in enumerate(arr):
        if not np.isfinite(row).all():
            raise EngineError(f"{poses_file}: row {i} ({photos[i].name}) has non-finite values")
        near, far = row[15], row[16]
        if not 0 < near < far:
            raise EngineError(
                f"{poses_file}: row {i} ({photos[i].name}): bounds near={near:g} far={far:g} are not 0 < near < far"
            )
        h_full, w_full, f_full = row[:15].reshape(3, 5)[:, 4]
        if not (h_full > 0 and w_full > 0 and f_full > 0):
            raise EngineError(
                f"{poses_file}: row {i} ({photos[i].name}): height, width, focal {h_full:g}, {w_full:g}, "
                f"{f_full:g} must be positive"
            )
    mats = arr[:, :15].reshape(-1, 3, 5)
    c2ws = np.tile(np.eye(4), (len(arr), 1, 1))
    c2ws[:, :3, 0], c2ws[:, :3, 1], c2ws[:, :3, 2] = mats[:, :, 1], -mats[:, :, 0], mats[:, :, 2]
    c2ws[:, :3, 3] = mats[:, :, 3]
    for i, m in enumerate(c2ws):
        r = m[:3, :3]
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-3) or np.linalg.det(r) < 0:
            raise EngineError(
                f"{poses_file}: row {i} ({photos[i].name}): the rotation is not a rotation "
                "(columns not orthonormal or mirrored)"
            )
    w, h = image_size(photos[0])
    if w < extra or h < extra:
        raise EngineError(f"{photos[0]}: image {w}x{h} is smaller than --downscale {extra}")
    hwf = mats[:, :, 4]
    fx, fy = hwf[:, 2] * w / hwf[:, 1], hwf[:, 2] * h / hwf[:, 0]
    near, far = arr[:, 15], arr[:, 16]

    # Upright (mean up → +Z: the rotation part of prepare's orientation, which depends only on up).
    T = orientation(c2ws)
    R = T[:3, :3] / np.cbrt(np.linalg.det(T[:3, :3]))
    up = np.eye(4)
    up[:3, :3] = R
    c2ws = apply_to_cameras(up, c2ws)
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    inner = _frustum_box(c2ws, tan_x, tan_y, near, 2.0 / (1.0 / near + 1.0 / far))
    whole = _frustum_box(c2ws, tan_x, tan_y, near, far)
    centre = inner.mean(0)
    spread = float(np.linalg.norm(c2ws[:, :3, 3] - centre, axis=1).mean())
    s = CAMERA_DISTANCE / spread if spread > 0 else 1.0
    move = np.eye(4)
    move[:3, :3] *= s
    move[:3, 3] = -s * centre
    c2ws = apply_to_cameras(move, c2ws)
    cameras = [
        Camera(
            c2ws[i],
            float(fx[i]),
            float(fy[i]),
            w / 2.0,
            h / 2.0,
            int(w),
            int(h),
            frame_name(p.name, f"{folder}: {p.name}"),
        )
        for i, p in enumerate(photos)
    ]
    meta = {"images_folder": folder.name + "/", "similarity": (move @ up).tolist(), "bounds": arr[:, 15:].tolist()}
    return FrameSource(
        cameras,
        photos,
        str(root),
        "llff",
        ((whole - centre) * s).astype(np.float32),
        ((inner - centre) * s).astype(np.float32),
        extra,
        meta=meta,
        size_keys="the first image says",
        n_listed=len(photos),
    )
