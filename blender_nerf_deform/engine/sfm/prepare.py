"""`prepare`'s stage: a folder of photos → a transforms.json dataset, by structure from motion.

pycolmap (the bindings of COLMAP itself, CPU wheels on PyPI) does the work: SIFT
features, exhaustive or sequential matching, incremental mapping, all on the CPU.
Why not a hand-written pipeline: COLMAP is the reference every NeRF tool's data
preparation uses (instant-ngp's colmap2nerf, nerfstudio's ns-process-data); its
bundle adjustment and camera model estimation are not something to rewrite.

All photos are taken as one camera (a phone or camera capture; COLMAP's SINGLE
mode) with the OPENCV model (focal lengths, principal point, k1 k2 p1 p2), which
the dataset loader turns into rays through the distorted pixels. The result is
oriented by `orient.py` and written, with the photos it registered, into a
temporary folder beside the destination that is renamed at the end: a failed or
interrupted run leaves nothing under DATASET_DIR (nor the parent folders it made).

COLMAP logs every photo, match and bundle adjustment to stderr (hundreds of lines for a real
capture); `prepare` lets through its warnings and errors only unless `colmap_log` asks for all
of it (`--colmap-log`): the stage lines above say where the run is.

Progress and cancelling (the worker's `prepare` op, Blender's Import Photos):
`progress(fraction, message)` is called as each stage starts and as the mapping
registers each photo; it may raise to stop the run between stages. `should_stop()`
is polled while pycolmap works and stops it midway through its cancellation token
(features, matching and mapping all take one); the run then raises PrepareCancelled.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..errors import EngineError
from ..files import check_writable
from . import IMAGE_SUFFIXES
from .colmap_cameras import reconstruction_cameras
from .orient import apply_to_cameras, orientation

MATCHERS = ("exhaustive", "sequential")
# Where each stage starts in the progress fraction: roughly each stage's share of a run's time on a small
# capture (mapping takes the longest, features and matching about a quarter each).
STAGE_START = {"features": 0.0, "matching": 0.2, "mapping": 0.45, "writing": 0.95}
# A failed run whose photos' longest side is below this says they are small (_small_photos_hint).
SMALL_PHOTO_PX = 1000


class PrepareCancelled(Exception):
    """`should_stop()` asked the run to stop; nothing was written."""


@contextmanager
def _cancellation(pycolmap, should_stop: Callable[[], bool] | None, poll_s: float = 0.1):
    """A pycolmap CancellationToken that a watcher thread cancels once `should_stop()` says so."""
    token = pycolmap.CancellationToken()
    if should_stop is None:
        yield token
        return
    done = threading.Event()

    def watch():
        while not done.wait(poll_s):
            if should_stop():
                token.cancel()
                return

    watcher = threading.Thread(target=watch, name="prepare-cancel", daemon=True)
    watcher.start()
    try:
        yield token
    except InterruptedError:
        if token.is_cancelled:
            raise PrepareCancelled() from None
        raise
    finally:
        done.set()
        watcher.join()


def photos_in(folder: Path) -> list[str]:
    if not folder.is_dir():
        raise EngineError(f"--images {folder}: no such folder")
    names = sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix in IMAGE_SUFFIXES)
    if len(names) < 3:
        raise EngineError(
            f"--images {folder}: {len(names)} photos (.jpg/.png) found; structure from motion needs at least 3"
        )
    return names


def _small_photos_hint(folder: Path, names: list[str]) -> str:
    """What a failed run's error adds when its photos are small: SIFT finds a few hundred features in
    a 200-px photo (a renderer's output, a dataset's downscaled copies), often too few to match
    (80 renders of a textured room at 200 px, 23 degrees apart: 2 registered)."""
    from PIL import Image

    sizes = []
    for name in names:
        try:
            with Image.open(folder / name) as im:
                sizes.append(im.size)
        except Exception:
            continue  # COLMAP has said what it could not read
    if not sizes:
        return ""
    w, h = sorted(sizes, key=max)[len(sizes) // 2]
    if max(w, h) >= SMALL_PHOTO_PX:
        return ""
    return f"; the photos are small ({w}x{h}): if you have them at full size, use those"


def check_one_size(folder: Path, names: list[str]) -> None:
    """EngineError naming the odd photos when the photos differ in size. COLMAP takes them as one camera
    (SINGLE mode) sized by the first photo by name and skips every photo of another size: an odd first
    photo registered none of the rest, reported as too little texture or overlap."""
    from collections import Counter

    from PIL import Image

    sizes = {}
    for name in names:
        try:
            with Image.open(folder / name) as im:  # reads the header only
                sizes[name] = im.size
        except Exception:
            continue  # COLMAP says what it cannot read
    counts = Counter(sizes.values())
    if len(counts) < 2:
        return
    (w, h), n_common = counts.most_common(1)[0]
    odd = [name for name, size in sizes.items() if size != (w, h)]
    shown = ", ".join(f"{name} is {sizes[name][0]}x{sizes[name][1]}" for name in odd[:5])
    more = f" and {len(odd) - 5} more differ" if len(odd) > 5 else ""
    raise EngineError(
        f"--images {folder}: the photos must all have one size (prepare takes them as one camera), but "
        f"{shown}{more}, where {n_common} of the {len(sizes)} photos are {w}x{h}: resize those or "
        "leave them out"
    )


def _place(src: Path, dst: Path) -> None:
    """Hard-link a photo into the dataset (no copy on the same disk), or copy it."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def transforms_for(cameras: list[dict], image_folder: str = "images") -> dict:
    """transforms.json (instant-ngp / nerfstudio keys) of oriented cameras: shared intrinsics at the
    top when all frames have one camera, per frame otherwise."""
    shared = all(c["intrinsics"] == cameras[0]["intrinsics"] for c in cameras)
    out: dict = dict(cameras[0]["intrinsics"]) if shared else {}
    if shared and out["camera_model"] == "OPENCV_FISHEYE":
        out["is_fisheye"] = True
    frames = []
    for c in cameras:
        frame = {"file_path": f"{image_folder}/{c['name']}", "transform_matrix": np.asarray(c["c2w"]).tolist()}
        if not shared:
            frame.update(c["intrinsics"])
        frames.append(frame)
    out["frames"] = frames
    return out


def prepare(
    images: str | os.PathLike,
    out: str | os.PathLike,
    matcher: str = "exhaustive",
    max_size: int = 1600,
    seed: int = 0,
    log=print,
    progress: Callable[[float, str], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    colmap_log: bool = False,
) -> dict:
    """Run structure from motion on the photos in `images`, write `out`/transforms.json + `out`/images/.

    Returns a summary: registered and unregistered photos, timings, the camera model found.
    `progress`, `should_stop` and `colmap_log`: the module docstring.
    """
    import pycolmap

    src, dst = Path(images), Path(out)
    if matcher not in MATCHERS:
        raise EngineError(f"--matcher {matcher!r}: one of {', '.join(MATCHERS)}")
    if not max_size >= 64:
        raise EngineError(f"--max-size {max_size}: must be at least 64 pixels")
    names = photos_in(src)
    check_one_size(src, names)
    if dst.exists() and (not dst.is_dir() or any(dst.iterdir())):
        raise EngineError(f"--out {dst}: exists and is not an empty folder; choose a new one")
    check_writable(dst.parent, folder=True)  # the work folder is made beside the destination
    made = [d for d in (dst.parent, *dst.parent.parents) if not d.exists()]  # deepest first
    dst.parent.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    work = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", suffix=".tmp", dir=dst.parent))

    def stage(name: str, message: str) -> None:
        log(f"prepare: {message}")
        if progress is not None:
            progress(STAGE_START[name], message)

    registered_so_far = [0]

    def next_image() -> None:  # called by pycolmap's mapper (C++): must not raise
        registered_so_far[0] += 1
        if progress is not None:
            span = STAGE_START["writing"] - STAGE_START["mapping"]
            try:
                progress(
                    STAGE_START["mapping"] + span * min(registered_so_far[0] / len(names), 1.0),
                    f"mapping: {registered_so_far[0]} of {len(names)} photos placed",
                )
            except Exception:
                pass  # a cancel: the token stops the mapper

    log_level = pycolmap.logging.minloglevel  # glog's, process-wide: restored below
    pycolmap.logging.minloglevel = int(pycolmap.logging.INFO if colmap_log else pycolmap.logging.WARNING)
    try:
        database = work / "colmap" / "database.db"
        database.parent.mkdir()
        t0 = time.perf_counter()
        stage("features", f"features of {len(names)} photos (SIFT, longest side up to {max_size} px)")
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "OPENCV"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = int(max_size)
        with _cancellation(pycolmap, should_stop) as token:
            pycolmap.extract_features(
                database,
                src,
                image_names=names,
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
                cancellation_token=token,
            )
        timings["features_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        stage("matching", f"{matcher} matching")
        match = pycolmap.match_exhaustive if matcher == "exhaustive" else pycolmap.match_sequential
        with _cancellation(pycolmap, should_stop) as token:
            match(database, device=pycolmap.Device.cpu, cancellation_token=token)
        timings["matching_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        stage("mapping", "incremental mapping (bundle adjustment)")
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = int(seed)
        with _cancellation(pycolmap, should_stop) as token:
            maps = pycolmap.incremental_mapping(
                database,
                src,
                work / "colmap" / "sparse",
                options,
                next_image_callback=next_image,
                cancellation_token=token,
            )
        timings["mapping_s"] = time.perf_counter() - t0
        if not maps:
            raise EngineError(
                f"structure from motion registered none of the {len(names)} photos in {src}: COLMAP found no "
                "initial pair with enough matches (photos too different, too little texture or overlap)"
                + _small_photos_hint(src, names)
            )
        reconstruction = max(maps.values(), key=lambda r: r.num_reg_images())
        cameras = reconstruction_cameras(reconstruction)
        registered = {c["name"] for c in cameras}
        missing = [n for n in names if n not in registered]
        if len(cameras) < 3:
            raise EngineError(
                f"structure from motion registered only {len(cameras)} of {len(names)} photos in {src} "
                f"({len(maps)} separate reconstruction(s)); take more overlapping photos"
                + _small_photos_hint(src, names)
            )
        if missing:
            log(
                f"prepare: {len(missing)} of {len(names)} photos not registered, left out: {', '.join(missing[:10])}"
                + (" ..." if len(missing) > 10 else "")
            )
        points = np.array([p.xyz for p in reconstruction.points3D.values()]) if reconstruction.num_points3D() else None
        c2ws = np.stack([c["c2w"] for c in cameras])
        T = orientation(c2ws, points)
        for c, m in zip(cameras, apply_to_cameras(T, c2ws)):
            c["c2w"] = m
        stage("writing", f"writing the dataset ({len(cameras)} cameras)")
        (work / "images").mkdir()
        for c in cameras:
            _place(src / c["name"], work / "images" / c["name"])
        transforms = transforms_for(cameras)
        (work / "transforms.json").write_text(json.dumps(transforms, indent=1))
        shutil.rmtree(work / "colmap")
        summary = {
            "photos": len(names),
            "registered": len(cameras),
            "unregistered": missing,
            "timings": timings,
            "camera_model": transforms.get("camera_model", "per frame"),
            "points": 0 if points is None else len(points),
            "similarity": T.tolist(),
        }
        (work / "prepare.json").write_text(json.dumps(summary, indent=1))
        if dst.exists():
            dst.rmdir()  # empty (checked above)
        os.replace(work, dst)
        return summary
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        for folder in made:  # the parents this run made, when nothing else went into them
            try:
                folder.rmdir()
            except OSError:
                break
        raise
    finally:
        pycolmap.logging.minloglevel = log_level
