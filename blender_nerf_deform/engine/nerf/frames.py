"""What every dataset format shares: `NerfDataset`, the transforms.json camera keys, image and
mask reading, downscaling, and the box derived from the cameras (dataset.py says which format
gives which box). The formats' readers (dataset.py's transforms.json, llff.py,
colmap_model.py) each make a `FrameSource`; dataset.py turns it into a NerfDataset.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import EngineError
from ..sfm.orient import axes_focus
from .camera import Camera, Distortion

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_CAMERA_MODELS = {
    "PINHOLE": None,
    "SIMPLE_PINHOLE": None,
    "OPENCV": "opencv",
    "SIMPLE_RADIAL": "opencv",
    "RADIAL": "opencv",
    "OPENCV_FISHEYE": "fisheye",
}
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
FORMAT_LABELS = {
    "nerf-synthetic": "NeRF-synthetic transforms.json",
    "instant-ngp": "instant-ngp transforms.json",
    "nerfstudio": "nerfstudio transforms.json",
    "llff": "LLFF poses_bounds.npy",
    "colmap": "COLMAP model",
}


@dataclass
class NerfDataset:
    """Images (N, H, W, 4) float32 straight-alpha RGBA in [0,1] (None when loaded without images),
    cameras (one per frame), the boxes `aabb` (2, 3: the whole scene) and `inner_aabb` (2, 3: the
    object region, inside aabb; an unbounded model's inner box), the frames' names (file basenames
    without extension), `masks` (None, or (N, H, W) bool: True = the pixel counts in the loss; object
    masks are in the images' alpha instead, `mask_meaning` says which),
    `has_alpha` (some image has alpha < 1; without images: the NeRF-synthetic form), `source` (the
    file or folder read) and `source_format` (a key of FORMAT_LABELS)."""

    cameras: list
    aabb: np.ndarray
    names: list
    images: np.ndarray | None = None
    source: str = ""
    has_alpha: bool = True
    meta: dict = field(default_factory=dict)
    inner_aabb: np.ndarray | None = None
    masks: np.ndarray | None = None
    source_format: str = ""
    mask_meaning: str | None = None  # None: no masks; "object" (now the alpha) or "ignore" (`masks`): silhouettes.py
    mask_reason: str | None = None  # why the masks were read so (what the command line and Blender report)

    def __post_init__(self):
        if self.inner_aabb is None:
            self.inner_aabb = np.array(self.aabb, dtype=np.float32)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def width(self) -> int:
        return self.cameras[0].width

    @property
    def height(self) -> int:
        return self.cameras[0].height

    def describe(self) -> str:
        """What the command line prints: "60 frames (instant-ngp transforms.json) from PATH"."""
        label = FORMAT_LABELS.get(self.source_format, self.source_format or "dataset")
        folder = self.meta.get("images_folder") if self.source_format in ("llff", "colmap") else None
        return f"{len(self)} frames ({label}{', ' + folder if folder else ''}) from {self.source}"

    def subset(self, indices) -> NerfDataset:
        indices = list(indices)
        return dataclasses.replace(
            self,
            cameras=[self.cameras[i] for i in indices],
            names=[self.names[i] for i in indices],
            images=None if self.images is None else self.images[indices],
            masks=None if self.masks is None else self.masks[indices],
        )


@dataclass
class FrameSource:
    """What a format's reader hands to the common part: cameras at the resolution of their image
    files (before `extra_downscale`), the files (None where missing), and the boxes."""

    cameras: list
    image_paths: list
    source: str
    source_format: str
    aabb: np.ndarray | None = None  # None: derived from the cameras
    inner_aabb: np.ndarray | None = None  # None: the same as aabb
    extra_downscale: int = 1  # box filter still to apply to the files (LLFF from a finer folder)
    mask_paths: list | None = None  # per frame, None: no mask
    sharpness: list | None = None  # per frame, when every frame has one
    meta: dict = field(default_factory=dict)
    size_keys: str = "the camera"  # what states the cameras' image size, for errors
    missing_rel: list = field(default_factory=list)  # frames skipped for want of their image file
    n_listed: int = 0  # frames the source lists


def number(d: dict, key: str, where: str) -> float:
    try:
        v = float(d[key])
    except (TypeError, ValueError):
        raise EngineError(f"{where}: `{key}` is not a number ({d[key]!r})") from None
    if not math.isfinite(v):
        raise EngineError(f"{where}: `{key}` is not finite ({d[key]!r})")
    return v


def pixels(d: dict, key: str, where: str) -> int:
    """An image size in pixels: a positive whole number."""
    v = number(d, key, where)
    if v != int(v) or v < 1:
        raise EngineError(f"{where}: `{key}` must be a positive whole number of pixels, got {d[key]!r}")
    return int(v)


def field_of_view(d: dict, key: str, where: str) -> float:
    v = number(d, key, where)
    if not 0.0 < v < math.pi:
        raise EngineError(f"{where}: `{key}` = {d[key]!r} is not a field of view in radians (0 < angle < pi)")
    return v


def lens_of(d: dict, where: str) -> Distortion | None:
    """The lens of a camera's keys (None for a pinhole): nerfstudio's `camera_model`, instant-ngp's
    `is_fisheye`, and the coefficients k1-k4, p1, p2 (absent = 0)."""
    model = d.get("camera_model")
    if model is not None:
        if model not in _CAMERA_MODELS:
            raise EngineError(
                f"{where}: camera_model {model!r} is not supported (supported: {', '.join(sorted(_CAMERA_MODELS))})"
            )
        kind = _CAMERA_MODELS[model]
    else:
        kind = "fisheye" if d.get("is_fisheye") else "opencv"
    coefficients = {k: number(d, k, where) for k in _DISTORTION_KEYS if d.get(k) is not None}
    if kind is None:
        if any(coefficients.values()):
            raise EngineError(
                f"{where}: camera_model {model} has no distortion, but the frame gives "
                f"{', '.join(k for k, v in coefficients.items() if v)}"
            )
        return None
    if kind == "opencv" and coefficients.get("k4"):
        raise EngineError(
            f"{where}: `k4` = {coefficients['k4']} belongs to the fisheye model (set is_fisheye or "
            "camera_model OPENCV_FISHEYE), or to OpenCV's rational model, which is not supported"
        )
    if kind == "fisheye" and (coefficients.get("p1") or coefficients.get("p2")):
        raise EngineError(f"{where}: a fisheye camera has no tangential terms p1/p2")
    lens = Distortion(kind, **coefficients)
    return None if lens.is_identity else lens


def frame_name(rel: str, where: str) -> str:
    """The frame's name (its file_path's basename without extension), which `render` writes as <name>.png."""
    if "\0" in rel:
        raise EngineError(f"{where}: `file_path` {rel!r} holds a NUL byte")
    name = os.path.splitext(os.path.basename(rel))[0]
    if name in ("", ".", ".."):
        raise EngineError(
            f"{where}: `file_path` {rel!r} names no file (a frame needs a file name, "
            "not a folder: its render is written as <name>.png)"
        )
    return name


def find_image(root: Path, rel: str, where: str) -> Path:
    p = root / rel
    if p.is_file():
        return p
    if not p.suffix:
        for ext in _IMAGE_EXTS:
            if p.with_suffix(ext).is_file():
                return p.with_suffix(ext)
    raise EngineError(f"{where}: image {p} not found")


# PIL modes by how their values scale to [0, 1]: 16-bit grey is read as is (a convert to RGB
# would clip it to 8 bits: 50% grey became white); the 8-bit modes go through RGB(A).
_GREY16_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I")
_RGBA_MODES = ("LA", "La", "PA", "RGBa", "RGBA")
_RGB_MODES = ("1", "L", "P", "RGB", "CMYK", "YCbCr", "LAB", "HSV")


def load_image(path: Path) -> np.ndarray:
    """(H, W, 4) float32 straight-alpha RGBA in [0, 1]: 8-bit data / 255, 16-bit data / 65535."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode in _GREY16_MODES:
                grey = np.asarray(im).astype(np.float32)
                if mode == "I" and (grey.min() < 0 or grey.max() > 65535):
                    raise EngineError(
                        f"{path}: 32-bit integer image with values {grey.min():g}..{grey.max():g} "
                        "outside 0..65535: save it as an 8- or 16-bit PNG"
                    )
                grey /= 65535.0
                return np.concatenate(
                    [np.repeat(grey[..., None], 3, axis=-1), np.ones(grey.shape + (1,), np.float32)], axis=-1
                )
            if mode in _RGBA_MODES or (mode in _RGB_MODES and "transparency" in im.info):
                im = im.convert("RGBA")
            elif mode in _RGB_MODES:
                im = im.convert("RGB")
            else:
                raise EngineError(f"{path}: unsupported image mode {mode!r} (use 8- or 16-bit RGB, RGBA or grey)")
            arr = np.asarray(im)
    except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError) as exc:
        raise EngineError(f"{path}: cannot read image ({exc})") from None
    arr = arr.astype(np.float32) / 255.0
    if arr.shape[-1] == 3:
        arr = np.concatenate([arr, np.ones(arr.shape[:2] + (1,), np.float32)], axis=-1)
    return arr


def downscale_image(img: np.ndarray, k: int) -> np.ndarray:
    """Box filter by an integer factor on premultiplied colour; crops the remainder at right/bottom."""
    h, w = img.shape[0] // k * k, img.shape[1] // k * k
    img = img[:h, :w]
    pre = np.concatenate([img[..., :3] * img[..., 3:4], img[..., 3:4]], axis=-1)
    pre = pre.reshape(h // k, k, w // k, k, 4).mean(axis=(1, 3))
    a = pre[..., 3:4]
    rgb = np.where(a > 0, pre[..., :3] / np.maximum(a, 1e-12), 0.0)
    return np.concatenate([rgb, a], axis=-1).astype(np.float32)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the image's header."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, UnidentifiedImageError, ValueError) as exc:
        raise EngineError(f"{path}: cannot read image ({exc})") from None


def load_mask(path: Path) -> np.ndarray:
    """(H, W) bool, True where the mask image is not 0 (nerfstudio: 0 = the pixel is ignored)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()
            arr = np.asarray(im.convert("RGB") if im.mode == "P" else im)
    except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError) as exc:
        raise EngineError(f"{path}: cannot read mask image ({exc})") from None
    if arr.ndim == 3:
        arr = arr[..., :3].max(axis=-1)  # a colour mask: any non-black pixel counts (alpha ignored)
    return arr > 0


def downscale_mask(mask: np.ndarray, k: int) -> np.ndarray:
    """A downscaled pixel counts only when all its k x k source pixels do (the crop of downscale_image)."""
    h, w = mask.shape[0] // k * k, mask.shape[1] // k * k
    return mask[:h, :w].reshape(h // k, k, w // k, k).all(axis=(1, 3))


def laplacian_sharpness(img: np.ndarray) -> float:
    """Variance of the Laplacian of the luma (colmap2nerf's `sharpness`, here on [0, 1] values)."""
    luma = (img[..., :3] * img[..., 3:4]) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    lap = 4 * luma[1:-1, 1:-1] - luma[:-2, 1:-1] - luma[2:, 1:-1] - luma[1:-1, :-2] - luma[1:-1, 2:]
    return float(lap.var()) if lap.size else 0.0


def scaled_camera(cam: Camera, k: int) -> Camera:
    """The camera of its images box-filtered by k: intrinsics / k, size // k (the remainder cropped)."""
    if k == 1:
        return cam
    return dataclasses.replace(
        cam, fx=cam.fx / k, fy=cam.fy / k, cx=cam.cx / k, cy=cam.cy / k, width=cam.width // k, height=cam.height // k
    )


def check_c2w(m, where: str, key: str = "transform_matrix") -> np.ndarray:
    """A finite 4x4 camera-to-world matrix (3x4 accepted) or an EngineError naming `where`."""
    try:
        c2w = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise EngineError(f"{where}: `{key}` is not a 4x4 matrix of numbers") from None
    if c2w.shape == (3, 4):
        c2w = np.concatenate([c2w, [[0, 0, 0, 1]]])
    if c2w.shape != (4, 4):
        raise EngineError(f"{where}: `{key}` has shape {c2w.shape}, expected 4x4")
    if not np.isfinite(c2w).all():
        raise EngineError(f"{where}: `{key}` has non-finite values")
    return c2w


def camera_from_keys(keys: dict, c2w: np.ndarray, w: int, h: int, name: str, where: str) -> Camera:
    """A camera of transforms.json keys (fl_x/fl_y/cx/cy or camera_angle_x/y, and the lens keys)
    for images of w x h pixels."""
    lens = lens_of(keys, where)
    if "fl_x" in keys:
        fx = number(keys, "fl_x", where)
        fy = number(keys, "fl_y", where) if "fl_y" in keys else fx
        cx = number(keys, "cx", where) if "cx" in keys else w / 2.0
        cy = number(keys, "cy", where) if "cy" in keys else h / 2.0
    elif "camera_angle_x" in keys:
        ax = field_of_view(keys, "camera_angle_x", where)
        fx = 0.5 * w / math.tan(0.5 * ax)
        fy = 0.5 * h / math.tan(0.5 * field_of_view(keys, "camera_angle_y", where)) if "camera_angle_y" in keys else fx
        cx, cy = w / 2.0, h / 2.0
    else:
        raise EngineError(f"{where}: missing key `camera_angle_x` or `fl_x` (no camera intrinsics)")
    if fx <= 0 or fy <= 0:
        raise EngineError(f"{where}: focal length must be positive (fx={fx}, fy={fy})")
    return Camera(c2w, fx, fy, cx, cy, int(w), int(h), name, lens)


def _axes_centre(cameras: list) -> tuple[np.ndarray, float]:
    """The point nearest to all optical axes (least squares; the cameras' mean position when the
    axes are near parallel) and the mean camera distance from it."""
    origins = np.stack([c.c2w[:3, 3] for c in cameras]).astype(np.float64)
    centre = axes_focus(origins, np.stack([-c.c2w[:3, 2] for c in cameras]).astype(np.float64))
    if centre is None:
        centre = origins.mean(axis=0)
    return centre, max(float(np.linalg.norm(origins - centre, axis=1).mean()), 1e-3)


def derive_aabb(cameras: list) -> np.ndarray:
    """A capture's box from its cameras alone: centred where their optical axes meet, the mean camera
    distance from the centre to each face, so the cameras stand on (or inside) it, as nerfacto and
    mip-NeRF 360 place their uncontracted region. Smaller boxes (what the images frame) cost held-out
    quality on both real and synthetic captures: what lies near the object (the wall behind the fox,
    the room's floor) is modelled at full resolution, and the render step (the box's diagonal / 256) is
    not needlessly fine."""
    centre, dist = _axes_centre(cameras)
    return np.stack([centre - dist, centre + dist]).astype(np.float32)
