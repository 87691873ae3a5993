"""Datasets: cameras + images, for training, evaluation and rendering, from every common format.

`load_dataset(path)` is the one entry point (train, eval, render --cameras). It recognises,
in this order:

1. a transforms.json (the file, or a folder holding transforms.json / transforms_train.json):
   NeRF-synthetic, instant-ngp or nerfstudio form (below);
2. LLFF: a folder with `poses_bounds.npy` and `images/`, `images_N/` (or one of those image
   folders itself): llff.py;
3. a COLMAP sparse model (cameras, images, points3D; .bin or .txt) in the folder, in its
   `sparse/0/` or `sparse/`, or the model folder itself, with the photos in `images/`
   beside it: colmap_model.py.

transforms.json keys (at the top level, any of them overridable per frame):

- NeRF-synthetic: `camera_angle_x` (horizontal field of view, radians; optional
  `camera_angle_y`), square pixels, principal point at the image centre.
- instant-ngp / nerfstudio: `fl_x`, `fl_y` (pixels), `cx`, `cy`, `w`, `h`, and the
  lens: OpenCV radial-tangential `k1 k2 k3 p1 p2`, or fisheye `k1-k4` with
  instant-ngp's `is_fisheye` or nerfstudio's `camera_model` OPENCV_FISHEYE
  (`camera_model` PINHOLE / OPENCV / OPENCV_FISHEYE; others are refused by
  name). Rays go through the distorted pixels (lens.py).
- nerfstudio's `applied_transform` (3x4) records the transform ns-process-data applied to
  COLMAP's poses: the `transform_matrix` poses are already in the file's world, and
  nerfstudio's own parser only composes it into its export transform (to bring COLMAP-frame
  points along). So it changes no camera here: it is checked (3x4, finite) and kept in
  `meta`. The cameras stay in the file's world, as instant-ngp keeps them (nerfstudio's
  parser re-orients and rescales at load time; we do not, so that cameras written for a
  dataset, `render --cameras`, stay in its frame).
- nerfstudio's per-frame `mask_path`: a mask image of the photo's size (0 = the pixel does
  not count in the loss) → `NerfDataset.masks`; frames without one count everywhere.
- instant-ngp's per-frame `sharpness` (variance of the Laplacian, from colmap2nerf): used by
  `min_sharpness_quantile` (below) when every frame has one.

Frames whose image file is missing are skipped with a warning, as instant-ngp
does (its fox lists 67 frames for 50 photos in its own repository); a dataset
with none left is an error.

Frames: `file_path` (relative to the json's folder; a path without extension
tries .png, .jpg, .jpeg) and `transform_matrix` (camera-to-world 4x4,
Blender/OpenGL convention). Images: PNG/JPG, RGB or RGBA (straight alpha), all
the same size. `downscale=k` box-filters images by an integer factor k
(premultiplied, so edges do not darken) and scales the intrinsics.

Two boxes, in the json's world: `aabb`, the whole scene (what a bounded NeRF models), and
`inner_aabb`, the object region (the inner box of an unbounded model, where cages and edit
regions live), the same as `aabb` unless said below. In this order:
1. `aabb`: [[xmin, ymin, zmin], [xmax, ymax, zmax]] in the json: both boxes. With an
   `aabb_scale` s as well, `aabb` becomes instant-ngp's scene: the cube of s times the box's
   longest side about its centre (instant-ngp fits that box's cube to its unit cube);
2. instant-ngp's `aabb_scale`, `scale`, `offset`: instant-ngp maps a world point p to its
   unit cube as q = cycle(scale * p + offset), cycle(x, y, z) = (y, z, x) (nerf_loader.h,
   nerf_position_to_ngp: the offset is added in the json's axis order, before the cycle;
   defaults scale 0.33, offset 0.5), and its scene is the cube of side aabb_scale (a power
   of two, 1 to 128) about q = (0.5, 0.5, 0.5). `inner_aabb` is the unit cube [0, 1]^3
   mapped back ([-1.515, 1.515]^3 with the defaults: 0.5 / 0.33), grown to the box derived
   from the cameras (4. below: they stand on its faces) within the scene cube, `aabb` the
   scene cube;
3. NeRF-synthetic form (`camera_angle_x`): [-1.5, 1.5]^3, as docs/ARCHITECTURE.md's Conventions state;
4. otherwise derived from the cameras (prepare's output, nerfstudio, COLMAP models):
   centred on the point closest (least squares) to all optical axes, half-width =
   the mean camera distance to that point, so the cameras stand on or inside it
   (frames.derive_aabb says why not smaller).

`min_sharpness_quantile=q` (0 keeps all) drops the blurriest fraction q of the frames (by
their `sharpness` when every frame has one, else by the variance of the Laplacian of the
loaded images' luma, as colmap2nerf computes `sharpness`). instant-ngp's own
`sharpness_discard_threshold` compares each frame with its neighbours' mean instead; a
fraction says plainly how many frames go.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..errors import EngineError
from ..sfm import photo_names
from .frames import (
    FORMAT_LABELS,
    FrameSource,
    NerfDataset,
    camera_from_keys,
    check_c2w,
    derive_aabb,
    downscale_image,
    downscale_mask,
    find_image,
    frame_name,
    image_size,
    laplacian_sharpness,
    lens_of,
    load_image,
    load_mask,
    number,
    pixels,
    scaled_camera,
)
from .silhouettes import MASK_MEANINGS, hull_box, mask_meaning

log = logging.getLogger(__name__)

__all__ = ["FORMAT_LABELS", "NerfDataset", "load_dataset"]

# instant-ngp's defaults (nerf_loader.h: NERF_SCALE, offset 0.5) and its largest aabb_scale
# (its occupancy grid has at most 8 cascades: 2^7).
NGP_SCALE = 0.33
NGP_OFFSET = (0.5, 0.5, 0.5)
NGP_MAX_AABB_SCALE = 128
_NERFSTUDIO_KEYS = ("camera_model", "applied_transform", "applied_scale", "mask_path", "orientation_override")
_NGP_KEYS = ("fl_x", "fl_y", "aabb_scale", "scale", "offset", "is_fisheye", "sharpness")


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


def _transforms_format(meta: dict, frames: list) -> str:
    dicts = [meta] + [f for f in frames if isinstance(f, dict)]
    if any(k in d for d in dicts for k in _NERFSTUDIO_KEYS):
        return "nerfstudio"
    if any(k in d for d in dicts for k in _NGP_KEYS):
        return "instant-ngp"
    return "nerf-synthetic" if "camera_angle_x" in meta else "instant-ngp"


def _aabb_scale(meta: dict, where: str) -> float:
    s = number(meta, "aabb_scale", where)
    if not (1 <= s <= NGP_MAX_AABB_SCALE and s == int(s) and (int(s) & (int(s) - 1)) == 0):
        raise EngineError(
            f"{where}: `aabb_scale` = {meta['aabb_scale']!r} must be a power of two from 1 to "
            f"{NGP_MAX_AABB_SCALE} (instant-ngp's scene is that many unit cubes wide)"
        )
    return s


def _transforms_boxes(meta: dict, where: str):
    """(aabb, inner_aabb) of the json's keys (module docstring), or (None, None): derive them."""
    if "aabb" in meta:
        try:
            box = np.asarray(meta["aabb"], dtype=np.float64).reshape(2, 3)
        except (TypeError, ValueError):
            raise EngineError(f"{where}: `aabb` must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]") from None
        if not np.isfinite(box).all() or not (box[1] > box[0]).all():
            raise EngineError(f"{where}: `aabb` {meta['aabb']} is not a finite non-empty box")
        if "aabb_scale" not in meta:
            return box.astype(np.float32), box.astype(np.float32)
        half = 0.5 * _aabb_scale(meta, where) * float((box[1] - box[0]).max())
        centre = box.mean(axis=0)
        return np.stack([centre - half, centre + half]).astype(np.float32), box.astype(np.float32)
    if any(k in meta for k in ("aabb_scale", "scale", "offset")):
        a = _aabb_scale(meta, where) if "aabb_scale" in meta else 1.0
        scale = number(meta, "scale", where) if "scale" in meta else NGP_SCALE
        if scale <= 0:
            raise EngineError(f"{where}: `scale` must be positive, got {meta['scale']!r}")
        offset = meta.get("offset", NGP_OFFSET)
        try:
            offset = np.broadcast_to(np.asarray(offset, dtype=np.float64), (3,)).copy()
        except (TypeError, ValueError):
            raise EngineError(f"{where}: `offset` must be a number or [x, y, z], got {meta['offset']!r}") from None
        if not np.isfinite(offset).all():
            raise EngineError(f"{where}: `offset` {meta['offset']!r} is not finite")

        # The cubes are centred on q = 0.5 on every axis, so the axis cycle leaves them unchanged:
        # only p = (q - offset) / scale, per json axis.
        def back(lo, hi):
            return np.stack([(lo - offset) / scale, (hi - offset) / scale]).astype(np.float32)

        return back(0.5 - 0.5 * a, 0.5 + 0.5 * a), back(0.0, 1.0)
    if "camera_angle_x" in meta:
        box = np.array([[-1.5] * 3, [1.5] * 3], dtype=np.float32)
        return box, box.copy()
    return None, None


def _grown_to_the_cameras(inner: np.ndarray, scene: np.ndarray, cameras: list) -> np.ndarray:
    """instant-ngp's unit cube grown to the box derived from the cameras (frames.derive_aabb: the cameras
    on its faces), within the scene cube. instant-ngp models its whole scene cube at full resolution, so a
    capture may put its object partly outside the unit cube (the fox's nose reaches 2.5 from the centre,
    the cube 1.515), and a capture shot all around puts the space between the cameras and the object
    outside it (gold_cape: the cameras 4 away): there a contracted background would model, coarsely,
    what every photo looks through. An `aabb` in the json overrides all this."""
    seen = derive_aabb(cameras)
    grown = np.stack([np.minimum(inner[0], seen[0]), np.maximum(inner[1], seen[1])])
    return np.clip(grown, scene[0], scene[1]).astype(np.float32)


def _read_transforms(jpath: Path, downscale: int, load_images: bool) -> FrameSource:
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
    lens_of(meta, str(jpath))
    if "applied_transform" in meta:
        m = np.asarray(meta["applied_transform"], dtype=object)
        try:
            ok = m.shape in ((3, 4), (4, 4)) and np.isfinite(m.astype(np.float64)).all()
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise EngineError(f"{jpath}: `applied_transform` must be a finite 3x4 matrix")
    aabb, inner = _transforms_boxes(meta, str(jpath))

    cameras, paths, masks, sharpness, missing = [], [], [], [], []
    for n, fr in enumerate(frames):
        where = f"{jpath}: frames[{n}]"
        if not isinstance(fr, dict):
            raise EngineError(f"{where}: expected an object")
        cam_meta = {**meta, **{k: v for k, v in fr.items() if k not in ("file_path", "transform_matrix")}}
        lens_of(cam_meta, where)
        if "transform_matrix" not in fr:
            raise EngineError(f"{where}: missing key `transform_matrix`")
        c2w = check_c2w(fr["transform_matrix"], where)
        if "file_path" not in fr:
            raise EngineError(f"{where}: missing key `file_path`")
        rel = str(fr["file_path"])
        name = frame_name(rel, where)
        sized = "w" in cam_meta and "h" in cam_meta
        try:
            img_path = find_image(root, rel, where)
        except EngineError:
            if load_images:
                missing.append(rel)
                continue
            if not sized:
                raise  # cameras only (render): the size must be given, or read from the image header
            img_path = None
        if sized:
            w, h = pixels(cam_meta, "w", where), pixels(cam_meta, "h", where)
        else:
            w, h = image_size(img_path)
        k = downscale
        if w < k or h < k:
            raise EngineError(f"{where}: image {w}x{h} is smaller than --downscale {k}")
        cameras.append(camera_from_keys(cam_meta, c2w, w, h, name, where))
        paths.append(img_path)
        mask = None
        if fr.get("mask_path") is not None:
            mask = root / str(fr["mask_path"])
            if load_images and not mask.is_file():
                raise EngineError(f"{where}: mask image {mask} (`mask_path`) not found")
        masks.append(mask)
        sharpness.append(number(fr, "sharpness", where) if "sharpness" in fr else None)
    if not cameras:
        raise EngineError(f"{jpath}: none of its {len(frames)} frames has an image file (first: {root / missing[0]})")
    if inner is not None and "aabb" not in meta:
        inner = _grown_to_the_cameras(inner, aabb, cameras)
    return FrameSource(
        cameras,
        paths,
        str(jpath),
        _transforms_format(meta, frames),
        aabb,
        inner,
        downscale,
        masks if any(m is not None for m in masks) else None,
        sharpness if all(s is not None for s in sharpness) else None,
        meta,
        "`w`/`h` say",
        missing,
        len(frames),
    )


def _finish(
    src: FrameSource, load_images: bool, min_sharpness_quantile: float, masks_asked: str = "auto"
) -> NerfDataset:
    """Images, masks, boxes, sharpness filter: the part every format shares."""
    k = src.extra_downscale
    images, masks, size = [], [], None
    if load_images:
        for cam, path, mask_path in zip(src.cameras, src.image_paths, src.mask_paths or [None] * len(src.cameras)):
            img = load_image(path)
            h, w = img.shape[:2]
            if size is None:
                size = (h, w)
            elif (h, w) != size:
                raise EngineError(
                    f"{path}: image is {w}x{h}, the first frame's is "
                    f"{size[1]}x{size[0]}: all images must have the same size"
                )
            if (w, h) != (cam.width, cam.height):
                raise EngineError(f"{path}: image is {w}x{h} but {src.size_keys} {cam.width}x{cam.height}")
            if src.mask_paths is not None:
                mask = load_mask(mask_path) if mask_path is not None else np.ones((h, w), bool)
                if mask.shape != (h, w):
                    raise EngineError(
                        f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]}, its image {path} is {w}x{h}"
                    )
                masks.append(mask)
            images.append(img)
    meaning = why = None
    if masks:
        meaning, why = mask_meaning(masks, masks_asked)
        if meaning == "object":  # the mask is the photo's alpha: outside it, empty space
            for img, mask in zip(images, masks):
                img[..., 3] *= mask
            masks = []
    if k > 1:
        images = [downscale_image(img, k) for img in images]
        masks = [downscale_mask(mask, k) for mask in masks]
    if src.missing_rel:
        log.warning(
            "warning: %s: %d of %d frames have no image file and are skipped (first: %s)",
            src.source,
            len(src.missing_rel),
            src.n_listed,
            src.missing_rel[0],
        )
    cameras = [scaled_camera(c, k) for c in src.cameras]
    aabb = src.aabb if src.aabb is not None else derive_aabb(cameras)
    inner = src.inner_aabb if src.inner_aabb is not None else aabb.copy()
    imgs = np.stack(images) if images else None
    if meaning == "object":
        # The object is all there is: its box is what the silhouettes carve, within the cameras' reach.
        box = hull_box(cameras, [img[..., 3] > 0.5 for img in imgs], derive_aabb(cameras))
        if box is None:
            raise EngineError(
                f"{src.source}: the object masks leave no point inside all of them (are the masks "
                "inverted, or the poses not the photos'?); pass --masks ignore to train the photos "
                "with the masked pixels skipped"
            )
        aabb, inner = box, box.copy()
    ds = NerfDataset(
        cameras,
        np.asarray(aabb, np.float32),
        [c.name for c in cameras],
        imgs,
        src.source,
        bool((imgs[..., 3] < 1).any()) if imgs is not None else src.source_format == "nerf-synthetic",
        src.meta,
        np.asarray(inner, np.float32),
        np.stack(masks) if masks else None,
        src.source_format,
        meaning,
        why,
    )
    if min_sharpness_quantile:
        ds = _drop_blurry(ds, src.sharpness, min_sharpness_quantile)
    return ds


def _drop_blurry(ds: NerfDataset, sharpness, q: float) -> NerfDataset:
    if sharpness is None:
        if ds.images is None:
            raise EngineError(f"{ds.source}: dropping blurry frames needs per-frame `sharpness` or the images")
        sharpness = [laplacian_sharpness(img) for img in ds.images]
    n_drop = int(q * len(ds))
    if n_drop == 0:
        return ds
    order = np.argsort(np.asarray(sharpness, np.float64), kind="stable")
    log.info(
        "note: %s: dropped the %d blurriest of %d frames (sharpness below %.4g)",
        ds.source,
        n_drop,
        len(ds),
        sharpness[order[n_drop]],
    )
    return ds.subset(sorted(order[n_drop:].tolist()))


_LOOKED_FOR = (
    "transforms.json (instant-ngp, nerfstudio, NeRF-synthetic), poses_bounds.npy (LLFF), a COLMAP model "
    "(cameras, images, points3D .bin/.txt here, in sparse/0/, sparse/ or 0/)"
)


def load_dataset(
    path, downscale: int = 1, load_images: bool = True, min_sharpness_quantile: float = 0.0, masks: str = "auto"
) -> NerfDataset:
    """Load a dataset in any form the module docstring lists. Raises EngineError naming the file/key at fault.

    `min_sharpness_quantile` (train's --drop-blurry): drop that fraction of the frames, the blurriest.
    `masks` (train's --masks): what the frames' masks mean, "object", "ignore" or "auto" (silhouettes.py).
    """
    from . import colmap_model, llff

    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise EngineError(f"--downscale must be a positive integer, got {downscale!r}")
    downscale = int(downscale)
    q = min_sharpness_quantile
    if isinstance(q, bool) or not isinstance(q, (int, float, np.floating, np.integer)) or not 0 <= q < 1:
        raise EngineError(f"--drop-blurry must be a fraction from 0 up to (not including) 1, got {q!r}")
    p = Path(path)
    if not p.exists():
        raise EngineError(f"{p}: no such file or folder")
    if (
        p.is_file()
        and p.suffix.lower() == ".json"
        or p.is_dir()
        and any((p / n).is_file() for n in ("transforms.json", "transforms_train.json"))
    ):
        src = _read_transforms(_resolve_json(p), downscale, load_images)
    elif llff.find(p) is not None:
        src = llff.read(p, downscale, load_images)
    elif colmap_model.find(p) is not None:
        src = colmap_model.read(p, downscale, load_images)
    elif p.is_dir() and photo_names(p):
        raise EngineError(
            f"{p}: {len(photo_names(p))} photos and no cameras: find them first with `prepare --images "
            f"{p} --out DATASET_DIR` (structure from motion), then train on DATASET_DIR; in Blender, "
            "Import Photos does both"
        )
    elif p.is_dir():
        raise EngineError(
            f"{p}: no dataset in this folder: no transforms.json, and no poses_bounds.npy or COLMAP "
            f"model; looked for {_LOOKED_FOR}"
        )
    else:
        raise EngineError(
            f"{p}: not a dataset file: give a transforms.json, LLFF's poses_bounds.npy, a COLMAP "
            "model file, or the folder holding one"
        )
    if masks not in MASK_MEANINGS:
        raise EngineError(f"--masks {masks!r}: one of {', '.join(MASK_MEANINGS)}")
    return _finish(src, load_images, float(q), masks)
