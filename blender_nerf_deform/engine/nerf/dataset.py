"""transforms.json datasets: cameras + images, for training, evaluation and rendering.

Two forms are read (keys at the top level, any of them overridable per frame):

- NeRF-synthetic: `camera_angle_x` (horizontal field of view, radians; optional
  `camera_angle_y`), square pixels, principal point at the image centre.
- instant-ngp / nerfstudio: `fl_x`, `fl_y` (pixels), `cx`, `cy`, `w`, `h`, and the
  lens: OpenCV radial-tangential `k1 k2 k3 p1 p2`, or fisheye `k1-k4` with
  instant-ngp's `is_fisheye` or nerfstudio's `camera_model` OPENCV_FISHEYE
  (`camera_model` PINHOLE / OPENCV / OPENCV_FISHEYE; others are refused by
  name). Rays go through the distorted pixels (lens.py).

Frames whose image file is missing are skipped with a warning, as instant-ngp
does (its fox lists 67 frames for 50 photos in its own repository); a dataset
with none left is an error.

Frames: `file_path` (relative to the json's folder; a path without extension
tries .png, .jpg, .jpeg) and `transform_matrix` (camera-to-world 4x4,
Blender/OpenGL convention). Images: PNG/JPG, RGB or RGBA (straight alpha), all
the same size. `downscale=k` box-filters images by an integer factor k
(premultiplied, so edges do not darken) and scales the intrinsics.

Scene bounds (the aabb), in this order:
1. `aabb`: [[xmin, ymin, zmin], [xmax, ymax, zmax]] in the json;
2. `aabb_scale` (instant-ngp): the box [-1.5 s, 1.5 s]^3 (instant-ngp maps the
   NeRF-synthetic world [-1.5, 1.5]^3 to its unit cube and scales that by s);
3. NeRF-synthetic form (`camera_angle_x`): [-1.5, 1.5]^3, as DESIGN.md states;
4. otherwise derived from the cameras: centred on the point closest (least
   squares) to all optical axes, half-width = mean camera distance to that
   point x tan(half the narrower field of view): the largest centred object
   that every camera sees whole.
"""

from __future__ import annotations

import json
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import EngineError
from .camera import Camera, Distortion

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_CAMERA_MODELS = {"PINHOLE": None, "SIMPLE_PINHOLE": None, "OPENCV": "opencv", "SIMPLE_RADIAL": "opencv",
                  "RADIAL": "opencv", "OPENCV_FISHEYE": "fisheye"}
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


@dataclass
class NerfDataset:
    """Images (N, H, W, 4) float32 straight-alpha RGBA in [0,1] (None when loaded without images),
    cameras (one per frame), aabb (2, 3) and the frames' names (file_path basenames without extension)."""

    cameras: list
    aabb: np.ndarray
    names: list
    images: np.ndarray | None = None
    source: str = ""
    has_alpha: bool = True
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def width(self) -> int:
        return self.cameras[0].width

    @property
    def height(self) -> int:
        return self.cameras[0].height

    def subset(self, indices) -> "NerfDataset":
        indices = list(indices)
        return NerfDataset([self.cameras[i] for i in indices], self.aabb, [self.names[i] for i in indices],
                           None if self.images is None else self.images[indices], self.source, self.has_alpha, self.meta)


def _resolve_json(path) -> Path:
    p = Path(path)
    if p.is_dir():
        for name in ("transforms.json", "transforms_train.json"):
            if (p / name).is_file():
                return p / name
        raise EngineError(f"{p}: no transforms.json in this folder")
    if not p.is_file():
        raise EngineError(f"{p}: no such file or folder")
    return p


def _number(d: dict, key: str, where: str) -> float:
    try:
        v = float(d[key])
    except (TypeError, ValueError):
        raise EngineError(f"{where}: `{key}` is not a number ({d[key]!r})") from None
    if not math.isfinite(v):
        raise EngineError(f"{where}: `{key}` is not finite ({d[key]!r})")
    return v


def _pixels(d: dict, key: str, where: str) -> int:
    """An image size in pixels: a positive whole number."""
    v = _number(d, key, where)
    if v != int(v) or v < 1:
        raise EngineError(f"{where}: `{key}` must be a positive whole number of pixels, got {d[key]!r}")
    return int(v)


def _field_of_view(d: dict, key: str, where: str) -> float:
    v = _number(d, key, where)
    if not 0.0 < v < math.pi:
        raise EngineError(f"{where}: `{key}` = {d[key]!r} is not a field of view in radians (0 < angle < pi)")
    return v


def _lens(d: dict, where: str) -> Distortion | None:
    """The lens of a camera's keys (None for a pinhole): nerfstudio's `camera_model`, instant-ngp's
    `is_fisheye`, and the coefficients k1-k4, p1, p2 (absent = 0)."""
    model = d.get("camera_model")
    if model is not None:
        if model not in _CAMERA_MODELS:
            raise EngineError(f"{where}: camera_model {model!r} is not supported "
                              f"(supported: {', '.join(sorted(_CAMERA_MODELS))})")
        kind = _CAMERA_MODELS[model]
    else:
        kind = "fisheye" if d.get("is_fisheye") else "opencv"
    coefficients = {k: _number(d, k, where) for k in _DISTORTION_KEYS if d.get(k) is not None}
    if kind is None:
        if any(coefficients.values()):
            raise EngineError(f"{where}: camera_model {model} has no distortion, but the frame gives "
                              f"{', '.join(k for k, v in coefficients.items() if v)}")
        return None
    if kind == "opencv" and coefficients.get("k4"):
        raise EngineError(f"{where}: `k4` = {coefficients['k4']} belongs to the fisheye model (set is_fisheye or "
                          "camera_model OPENCV_FISHEYE), or to OpenCV's rational model, which is not supported")
    if kind == "fisheye" and (coefficients.get("p1") or coefficients.get("p2")):
        raise EngineError(f"{where}: a fisheye camera has no tangential terms p1/p2")
    lens = Distortion(kind, **coefficients)
    return None if lens.is_identity else lens


def _frame_name(rel: str, where: str) -> str:
    """The frame's name (its file_path's basename without extension), which `render` writes as <name>.png."""
    if "\0" in rel:
        raise EngineError(f"{where}: `file_path` {rel!r} holds a NUL byte")
    name = os.path.splitext(os.path.basename(rel))[0]
    if name in ("", ".", ".."):
        raise EngineError(f"{where}: `file_path` {rel!r} names no file (a frame needs a file name, "
                          "not a folder: its render is written as <name>.png)")
    return name


def _find_image(root: Path, rel: str, where: str) -> Path:
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


def _load_image(path: Path) -> np.ndarray:
    """(H, W, 4) float32 straight-alpha RGBA in [0, 1]: 8-bit data / 255, 16-bit data / 65535."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode in _GREY16_MODES:
                grey = np.asarray(im).astype(np.float32)
                if mode == "I" and (grey.min() < 0 or grey.max() > 65535):
                    raise EngineError(f"{path}: 32-bit integer image with values {grey.min():g}..{grey.max():g} "
                                      "outside 0..65535: save it as an 8- or 16-bit PNG")
                grey /= 65535.0
                return np.concatenate([np.repeat(grey[..., None], 3, axis=-1),
                                       np.ones(grey.shape + (1,), np.float32)], axis=-1)
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


def _downscale(img: np.ndarray, k: int) -> np.ndarray:
    """Box filter by an integer factor on premultiplied colour; crops the remainder at right/bottom."""
    h, w = img.shape[0] // k * k, img.shape[1] // k * k
    img = img[:h, :w]
    pre = np.concatenate([img[..., :3] * img[..., 3:4], img[..., 3:4]], axis=-1)
    pre = pre.reshape(h // k, k, w // k, k, 4).mean(axis=(1, 3))
    a = pre[..., 3:4]
    rgb = np.where(a > 0, pre[..., :3] / np.maximum(a, 1e-12), 0.0)
    return np.concatenate([rgb, a], axis=-1).astype(np.float32)


def _derive_aabb(cameras: list) -> np.ndarray:
    """Box centred where the optical axes meet (least squares), sized so every camera sees it whole."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    origins, axes = [], []
    for cam in cameras:
        o = cam.c2w[:3, 3]
        d = -cam.c2w[:3, 2] / np.linalg.norm(cam.c2w[:3, 2])
        m = np.eye(3) - np.outer(d, d)
        a += m
        b += m @ o
        origins.append(o)
        axes.append(d)
    try:
        center = np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        center = np.mean(origins, axis=0)
    dist = float(np.mean([np.linalg.norm(o - center) for o in origins]))
    half_fov = min(min(math.atan(0.5 * c.width / c.fx), math.atan(0.5 * c.height / c.fy)) for c in cameras)
    half = max(dist * math.tan(half_fov), 1e-3)
    return np.stack([center - half, center + half]).astype(np.float32)


def load_dataset(path, downscale: int = 1, load_images: bool = True) -> NerfDataset:
    """Load a transforms.json (or a folder holding one). Raises EngineError naming the file/key at fault."""
    jpath = _resolve_json(path)
    root = jpath.parent
    try:
        meta = json.loads(jpath.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise EngineError(f"{jpath}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise EngineError(f"{jpath}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise EngineError(f"{jpath}: expected a JSON object at the top level")
    frames = meta.get("frames")
    if frames is None:
        raise EngineError(f"{jpath}: missing key `frames`")
    if not isinstance(frames, list) or not frames:
        raise EngineError(f"{jpath}: `frames` is empty: the dataset has no images")
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise EngineError(f"--downscale must be a positive integer, got {downscale!r}")
    downscale = int(downscale)
    _lens(meta, str(jpath))

    cameras, names, images, missing = [], [], [], []
    size = None
    for n, fr in enumerate(frames):
        where = f"{jpath}: frames[{n}]"
        if not isinstance(fr, dict):
            raise EngineError(f"{where}: expected an object")
        cam_meta = {**meta, **{k: v for k, v in fr.items() if k not in ("file_path", "transform_matrix")}}
        lens = _lens(cam_meta, where)
        if "transform_matrix" not in fr:
            raise EngineError(f"{where}: missing key `transform_matrix`")
        try:
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise EngineError(f"{where}: `transform_matrix` is not a 4x4 matrix of numbers") from None
        if c2w.shape == (3, 4):
            c2w = np.concatenate([c2w, [[0, 0, 0, 1]]])
        if c2w.shape != (4, 4):
            raise EngineError(f"{where}: `transform_matrix` has shape {c2w.shape}, expected 4x4")
        if not np.isfinite(c2w).all():
            raise EngineError(f"{where}: `transform_matrix` has non-finite values")
        if "file_path" not in fr:
            raise EngineError(f"{where}: missing key `file_path`")
        rel = str(fr["file_path"])
        name = _frame_name(rel, where)
        img = None
        if load_images:
            try:
                img_path = _find_image(root, rel, where)
            except EngineError:
                missing.append(rel)
                continue
            img = _load_image(img_path)
            if size is None:
                size = img.shape[:2]
            elif img.shape[:2] != size:
                raise EngineError(f"{img_path}: image is {img.shape[1]}x{img.shape[0]}, the first frame's is "
                                  f"{size[1]}x{size[0]}: all images must have the same size")
            h, w = img.shape[:2]
            if "w" in cam_meta and _pixels(cam_meta, "w", where) != w or "h" in cam_meta and _pixels(cam_meta, "h", where) != h:
                raise EngineError(f"{img_path}: image is {w}x{h} but `w`/`h` say {cam_meta.get('w')}x{cam_meta.get('h')}")
        else:
            if "w" not in cam_meta or "h" not in cam_meta:
                # Cameras-only use (render): the size must be given, or read from the image header.
                img_path = _find_image(root, rel, where)
                from PIL import Image

                try:
                    with Image.open(img_path) as im:
                        w, h = im.size
                except OSError as exc:
                    raise EngineError(f"{img_path}: cannot read image ({exc})") from None
            else:
                w, h = _pixels(cam_meta, "w", where), _pixels(cam_meta, "h", where)
        if w <= 0 or h <= 0:
            raise EngineError(f"{where}: image size {w}x{h} is empty")
        if "fl_x" in cam_meta:
            fx = _number(cam_meta, "fl_x", where)
            fy = _number(cam_meta, "fl_y", where) if "fl_y" in cam_meta else fx
            cx = _number(cam_meta, "cx", where) if "cx" in cam_meta else w / 2.0
            cy = _number(cam_meta, "cy", where) if "cy" in cam_meta else h / 2.0
        elif "camera_angle_x" in cam_meta:
            ax = _field_of_view(cam_meta, "camera_angle_x", where)
            fx = 0.5 * w / math.tan(0.5 * ax)
            fy = 0.5 * h / math.tan(0.5 * _field_of_view(cam_meta, "camera_angle_y", where)) if "camera_angle_y" in cam_meta else fx
            cx, cy = w / 2.0, h / 2.0
        else:
            raise EngineError(f"{where}: missing key `camera_angle_x` or `fl_x` (no camera intrinsics)")
        if fx <= 0 or fy <= 0:
            raise EngineError(f"{where}: focal length must be positive (fx={fx}, fy={fy})")
        k = downscale
        if w < k or h < k:
            raise EngineError(f"{where}: image {w}x{h} is smaller than --downscale {k}")
        if img is not None and k > 1:
            img = _downscale(img, k)
        cameras.append(Camera(c2w, fx / k, fy / k, cx / k, cy / k, w // k, h // k, name, lens))
        names.append(name)
        if img is not None:
            images.append(img)

    if missing:
        if not cameras:
            raise EngineError(f"{jpath}: none of its {len(frames)} frames has an image file (first: {root / missing[0]})")
        print(f"warning: {jpath}: {len(missing)} of {len(frames)} frames have no image file and are skipped "
              f"(first: {missing[0]})", file=sys.stderr)
    if "aabb" in meta:
        try:
            aabb = np.asarray(meta["aabb"], dtype=np.float32).reshape(2, 3)
        except (TypeError, ValueError):
            raise EngineError(f"{jpath}: `aabb` must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]") from None
        if not np.isfinite(aabb).all() or not (aabb[1] > aabb[0]).all():
            raise EngineError(f"{jpath}: `aabb` {meta['aabb']} is not a finite non-empty box")
    elif "aabb_scale" in meta:
        s = _number(meta, "aabb_scale", str(jpath))
        if s <= 0:
            raise EngineError(f"{jpath}: `aabb_scale` must be positive, got {s}")
        aabb = np.array([[-1.5 * s] * 3, [1.5 * s] * 3], dtype=np.float32)
    elif "camera_angle_x" in meta:
        aabb = np.array([[-1.5] * 3, [1.5] * 3], dtype=np.float32)
    else:
        aabb = _derive_aabb(cameras)
    imgs = np.stack(images) if images else None
    return NerfDataset(cameras, aabb, names, imgs, str(jpath), meta=meta)
