"""A COLMAP sparse model (cameras, images, points3D; binary .bin or text .txt) with its photos.

Read with pycolmap (the bindings of COLMAP itself, already the engine's structure-from-motion
library): `pycolmap.Reconstruction(folder)` reads both forms, so no reader of COLMAP's files
is written here. engine/sfm/colmap_cameras.py turns its cameras and world-to-camera poses
(OpenCV axes) into OpenGL camera-to-world matrices and transforms.json lens keys.

Where: the model folder itself, or a folder with `sparse/0/` or `sparse/` holding it; the
photos are `images/` in the folder given, or beside the model (`../images`, `../../images`
for `sparse/0`). Registered images whose photo is missing are skipped with a warning.

Placed as `prepare` places a capture (engine/sfm/orient.py: the cameras' mean up → +Z,
centred where the optical axes meet, or on the sparse points' median when they barely
cross, cameras 4 units away), so that a model and the transforms.json `prepare` would write
from it give the same cameras; the box is then derived from the cameras, as for
`prepare`'s datasets (dataset.py, "derived").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import EngineError
from ..sfm.colmap_cameras import reconstruction_cameras, reconstruction_points
from ..sfm.orient import apply_to_cameras, orientation
from .frames import FrameSource, camera_from_keys, frame_name

MODEL_FILES = ("cameras", "images", "points3D")
_ROLES = {"cameras": "the camera models", "images": "the images' poses", "points3D": "the sparse points"}


def _has_model_file(folder: Path) -> bool:
    return any((folder / f"{n}.{ext}").is_file() for n in MODEL_FILES for ext in ("bin", "txt"))


def find(path: Path) -> Path | None:
    """The model folder `path` names (itself, its sparse/0/ or sparse/, or the folder of a model file), or None."""
    if path.is_file():
        return path.parent if path.stem in MODEL_FILES and path.suffix in (".bin", ".txt") else None
    for folder in (path, path / "sparse" / "0", path / "sparse", path / "0"):
        if folder.is_dir() and _has_model_file(folder):
            return folder
    return None


def _check_complete(model: Path) -> None:
    for ext in ("bin", "txt"):
        if all((model / f"{n}.{ext}").is_file() for n in MODEL_FILES):
            return
    ext = "bin" if any((model / f"{n}.bin").is_file() for n in MODEL_FILES) else "txt"
    missing = [f"{n}.{ext} ({_ROLES[n]})" for n in MODEL_FILES if not (model / f"{n}.{ext}").is_file()]
    hint = ""
    for up in (model.parent, model.parent.parent):
        if (up / "poses_bounds.npy").is_file():
            hint = f"; this capture's poses are in {up / 'poses_bounds.npy'}: load {up} (LLFF) instead"
            break
    raise EngineError(f"{model}: incomplete COLMAP model: no {', '.join(missing)}{hint}")


def _images_folder(path: Path, model: Path) -> list[Path]:
    """Where the photos may be, in order of preference."""
    candidates = [path / "images"] if path.is_dir() and path != model else []
    return candidates + [model / "images", model.parent / "images", model.parent.parent / "images"]


def read(path: Path, downscale: int, load_images: bool) -> FrameSource:
    import pycolmap

    model = find(path)
    _check_complete(model)
    try:
        rec = pycolmap.Reconstruction(str(model))
    except (ValueError, RuntimeError, OSError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise EngineError(f"{model}: cannot read the COLMAP model ({first})") from None
    try:
        cams = reconstruction_cameras(rec)
    except EngineError as exc:
        raise EngineError(f"{model}: {exc}") from None
    if not cams:
        raise EngineError(f"{model}: the COLMAP model has no registered image")
    candidates = _images_folder(path, model)
    images = next((c for c in candidates if c.is_dir()), None)
    if images is None:
        if load_images:
            raise EngineError(
                f"{model}: no folder of photos beside the COLMAP model (looked for "
                f"{', '.join(str(c) for c in dict.fromkeys(candidates))})"
            )
        images = candidates[0]
    c2ws = np.stack([c["c2w"] for c in cams])
    T = orientation(c2ws, reconstruction_points(rec))
    c2ws = apply_to_cameras(T, c2ws)
    cameras, paths, missing = [], [], []
    for c, c2w in zip(cams, c2ws):
        where = f"{model}: image {c['name']}"
        photo = images / c["name"]
        if not photo.is_file():
            if load_images:
                missing.append(c["name"])
                continue
            photo = None
        keys = c["intrinsics"]
        w, h = int(keys["w"]), int(keys["h"])
        if w < downscale or h < downscale:
            raise EngineError(f"{where}: image {w}x{h} is smaller than --downscale {downscale}")
        cameras.append(camera_from_keys(keys, c2w, w, h, frame_name(c["name"], where), where))
        paths.append(photo)
    if not cameras:
        raise EngineError(f"{model}: none of its {len(cams)} registered images is in {images} (first: {missing[0]})")
    meta = {"images_folder": str(images), "similarity": T.tolist(), "points": int(rec.num_points3D())}
    return FrameSource(
        cameras,
        paths,
        str(model),
        "colmap",
        extra_downscale=downscale,
        meta=meta,
        size_keys="COLMAP's camera says",
        missing_rel=missing,
        n_listed=len(cams),
    )
