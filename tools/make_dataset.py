#!/usr/bin/env python3
"""Render a NeRF dataset (transforms.json + RGBA PNGs) from any .blend, headless.

What BlenderNeRF does for instant-ngp users, from the command line and with
the `bpy` module (Blender as a Python module), no Blender UI:

    python tools/make_dataset.py --blend SCENE.blend --out DIR \
        [--count 100] [--radius 4] [--resolution 200 [200]] [--seed 0] \
        [--hemisphere | --min-elevation DEG] [--samples 16] [--test-count 0] \
        [--target X Y Z] [--opaque] [--aabb X0 Y0 Z0 X1 Y1 Z1] ...

Cameras sit on a sphere (or the upper hemisphere, +Z up; or the part of the
sphere above --min-elevation degrees) of the given radius around the target
point and look at it. Each view is rendered by Cycles on the CPU over a
transparent film and saved as an 8-bit RGBA PNG with straight (unassociated)
alpha: background alpha 0, opaque surfaces alpha 1. With --opaque the film is
not transparent and the views are 8-bit RGB PNGs (no alpha channel): what is
behind the object (a room, tools/make_room_scene.py) is part of the capture,
as in a real photograph, and the cameras may stand inside the scene. Cycles'
pixel filter is set to a one-pixel box, so a pixel is the average over its own
area, centred where the NeRF's ray goes. The view transform is "Standard"
unless --view-transform says otherwise (Blender 5's default AgX would tint
colours); the .blend on disk is never modified.

Why Cycles on the CPU: it needs no GPU or display. With the bpy module headless
(Blender 5.0.1, no GPU), Workbench renders through a software EGL context
(with EGL errors printed) and EEVEE spends ~30 s compiling shaders for one
64x48 view, while Cycles renders such a view in a few milliseconds to a tenth
of a second and is deterministic for a given --seed.

What is written (the NeRF-synthetic / instant-ngp form, read by the engine):

    DIR/transforms.json        training views
    DIR/images/r_<k>.png
    DIR/test/transforms.json   only with --test-count N > 0: N other random
    DIR/test/images/r_<k>.png  views, so that `engine eval --data DIR/test` works

transforms.json keys:
    camera_angle_x, camera_angle_y   field of view in radians (x: horizontal)
    fl_x, fl_y, cx, cy               focal lengths and principal point, pixels
    w, h                             image size, pixels
    frames[]: file_path              relative to the json's folder, extension included
              transform_matrix       camera-to-world 4x4: Blender's own
                                     `matrix_world` of the camera that rendered
                                     the view (no axis change)
    aabb                             only with --aabb: [[x0, y0, z0], [x1, y1, z1]], the
                                     box the object lies in (the engine's scene bounds)
    generator                        how the views were made (tool, options)

Camera convention (DESIGN.md): the camera looks down its local -Z with +Y up;
pixel (i, j) (column i, row j counted from the top of the image) is the ray

    d_camera = ((i + 0.5 - cx) / fl_x,  -(j + 0.5 - cy) / fl_y,  -1)

through the pixel centre. Without lens shift and with square pixels,
cx = w/2, cy = h/2 and fl_x = fl_y = 0.5 * w / tan(0.5 * camera_angle_x), so a
reader that only knows `camera_angle_x` gets the same rays. With `--shift` or
`--pixel-aspect` only the fl_x/fl_y/cx/cy form is exact.

Importable: `make_dataset(...)` does the same as the command line and returns
the paths it wrote. It loads the .blend into this process's Blender (the
`bpy` module is one process-wide Blender), replacing what was loaded; with
`blend=None` it renders the scene already loaded (its camera is added and
removed again, and the render settings it changes are restored).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

# The add-on's camera model lives in the package at the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
RENDERABLE_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT", "VOLUME", "POINTCLOUD", "CURVES", "GREASEPENCIL"}
SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")
CAMERA_NAME = "make_dataset_camera"


class DatasetError(Exception):
    """Bad input for the dataset tool; the message names the option, file or value at fault."""


@dataclass
class Options:
    """Everything that decides the views; defaults are NeRF-synthetic-like (50 mm on 36 mm, radius 4)."""

    count: int = 100
    radius: float = 4.0
    resolution: tuple[int, int] = (200, 200)
    seed: int = 0
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    hemisphere: bool = False
    min_elevation: float | None = None  # degrees; cameras from this elevation up to the zenith (None: sphere / hemisphere)
    layout: str = "spiral"  # "spiral": even Fibonacci spiral, turned by the seed; "random": uniform random
    samples: int = 16
    denoise: bool = False
    test_count: int = 0
    opaque: bool = False  # film not transparent, RGB images: the background is part of the capture
    aabb: tuple | None = None  # ((x0, y0, z0), (x1, y1, z1)) written as transforms.json's "aabb"
    lens: float = 50.0  # mm
    sensor_width: float = 36.0  # mm
    sensor_height: float = 24.0  # mm, used by sensor_fit VERTICAL
    sensor_fit: str = "AUTO"
    shift: tuple[float, float] = (0.0, 0.0)
    pixel_aspect: float = 1.0  # pixel width / pixel height (Blender's pixel_aspect_x / pixel_aspect_y)
    view_transform: str = "Standard"  # colour management view; "KEEP" keeps the .blend's
    threads: int = 0  # 0: all cores (Blender's AUTO)
    frame: int | None = None  # scene frame to render (None: the .blend's current frame)
    frame_prefix: str = "r_"
    extras: dict = field(default_factory=dict)  # free-form, copied into transforms.json's generator

    def validate(self) -> None:
        def positive(name, value):
            if not value > 0 or not math.isfinite(value):
                raise DatasetError(f"--{name.replace('_', '-')} must be > 0, got {value}")

        if not isinstance(self.count, int) or self.count < 1:
            raise DatasetError(f"--count must be a whole number >= 1, got {self.count!r}")
        if not isinstance(self.test_count, int) or self.test_count < 0:
            raise DatasetError(f"--test-count must be a whole number >= 0, got {self.test_count!r}")
        if not isinstance(self.samples, int) or self.samples < 1:
            raise DatasetError(f"--samples must be a whole number >= 1, got {self.samples!r}")
        if len(self.resolution) != 2 or any(not isinstance(v, int) or v < 1 for v in self.resolution):
            raise DatasetError(f"--resolution must be one or two whole numbers >= 1, got {self.resolution!r}")
        if max(self.resolution) > 16384:
            raise DatasetError(f"--resolution must be at most 16384 pixels a side, got {self.resolution!r}")
        for name in ("radius", "lens", "sensor_width", "sensor_height", "pixel_aspect"):
            positive(name, float(getattr(self, name)))
        if len(self.target) != 3 or not all(math.isfinite(v) for v in self.target):
            raise DatasetError(f"--target must be three finite numbers, got {self.target!r}")
        if len(self.shift) != 2 or not all(math.isfinite(v) for v in self.shift):
            raise DatasetError(f"--shift must be two finite numbers, got {self.shift!r}")
        if self.sensor_fit not in SENSOR_FITS:
            raise DatasetError(f"--sensor-fit must be one of {', '.join(SENSOR_FITS)}, got {self.sensor_fit!r}")
        if self.min_elevation is not None:
            if self.hemisphere:
                raise DatasetError("--hemisphere and --min-elevation exclude each other "
                                   "(--hemisphere is --min-elevation 0)")
            if not (math.isfinite(self.min_elevation) and -90.0 <= self.min_elevation < 90.0):
                raise DatasetError(f"--min-elevation must be in [-90, 90) degrees, got {self.min_elevation!r}")
        if self.aabb is not None:
            lo, hi = (tuple(map(float, c)) for c in self.aabb)
            if len(lo) != 3 or len(hi) != 3 or not all(map(math.isfinite, lo + hi)) or not all(a < b for a, b in zip(lo, hi)):
                raise DatasetError(f"--aabb must be six finite numbers X0 Y0 Z0 X1 Y1 Z1 with X0 < X1, Y0 < Y1, "
                                   f"Z0 < Z1, got {self.aabb!r}")
        if self.layout not in ("spiral", "random"):
            raise DatasetError(f"--layout must be spiral or random, got {self.layout!r}")
        if self.frame is not None and not isinstance(self.frame, int):
            raise DatasetError(f"--frame must be a whole number, got {self.frame!r}")
        if not isinstance(self.threads, int) or self.threads < 0:
            raise DatasetError(f"--threads must be a whole number >= 0 (0: all cores), got {self.threads!r}")
        if not self.frame_prefix or any(c in self.frame_prefix for c in "/\\"):
            raise DatasetError(f"frame prefix must be a non-empty file-name part, got {self.frame_prefix!r}")


# --------------------------------------------------------------------------- geometry (no bpy)


def camera_positions(count: int, radius: float, target=(0.0, 0.0, 0.0), hemisphere: bool = False,
                     seed: int = 0, layout: str = "spiral", min_elevation: float | None = None) -> np.ndarray:
    """(count, 3) camera centres on a sphere (or the upper, +Z, hemisphere) around `target`.

    "spiral": a Fibonacci spiral (even coverage even for a few dozen views), turned
    about Z by an angle drawn from the seed. "random": uniform on the (hemi)sphere.
    `min_elevation` (degrees, overrides `hemisphere`): only the cap above that elevation,
    evenly covered the same way (-90: the sphere, 0: the hemisphere).
    """
    rng = np.random.default_rng(seed)
    z_min = math.sin(math.radians(min_elevation)) if min_elevation is not None else (0.0 if hemisphere else -1.0)
    if layout == "spiral":
        k = np.arange(count) + 0.5
        z = 1.0 - k / count * (1.0 - z_min)
        phi = rng.uniform(0.0, 2.0 * math.pi) + GOLDEN_ANGLE * np.arange(count)
    elif layout == "random":
        z = rng.uniform(z_min, 1.0, count)
        phi = rng.uniform(0.0, 2.0 * math.pi, count)
    else:
        raise DatasetError(f"--layout must be spiral or random, got {layout!r}")
    s = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    unit = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)
    return np.asarray(target, dtype=np.float64) + radius * unit


def intrinsics(scene, cam_obj) -> dict:
    """fl_x, fl_y, cx, cy (pixels; cy from the top row), w, h and fields of view of a Blender camera.

    The add-on's own mapping of a Blender camera (sensor fit, shift, pixel
    aspect, resolution %) to a pinhole, so datasets and renders share one model.
    """
    from blender_nerf_deform.addon.camera import pinhole_from_blender  # needs bpy loaded

    pin = pinhole_from_blender(scene, cam_obj)
    return {"fl_x": pin.fx, "fl_y": pin.fy, "cx": pin.cx, "cy": pin.cy, "w": pin.width, "h": pin.height,
            "camera_angle_x": 2.0 * math.atan(0.5 * pin.width / pin.fx),
            "camera_angle_y": 2.0 * math.atan(0.5 * pin.height / pin.fy)}


def project(points, transform_matrix, fl_x, fl_y, cx, cy) -> np.ndarray:
    """Continuous pixel coordinates (x right, y down; pixel (i, j) spans [i, i+1) x [j, j+1)) of world points."""
    c2w = np.asarray(transform_matrix, dtype=np.float64)
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    cam = (np.linalg.inv(c2w) @ np.c_[p, np.ones(len(p))].T).T[:, :3]
    depth = -cam[:, 2]
    return np.stack([cx + fl_x * cam[:, 0] / depth, cy - fl_y * cam[:, 1] / depth], axis=1)


# --------------------------------------------------------------------------- files


def write_json_atomic(path: Path, data) -> None:
    from blender_nerf_deform.engine.files import atomic_write

    atomic_write(path, lambda f: f.write((json.dumps(data, indent=1) + "\n").encode()))


# --------------------------------------------------------------------------- Blender


def _import_bpy():
    try:
        import bpy  # noqa: PLC0415 (heavy: only when rendering)
    except ImportError as exc:  # pragma: no cover - depends on the interpreter
        raise DatasetError(f"the bpy module (Blender as a Python module) is not importable here: {exc}") from exc
    return bpy


def _check_blend_file(blend: Path) -> None:
    """Fail fast (before Blender starts) on a missing or foreign file."""
    if not blend.is_file():
        raise DatasetError(f"--blend: no such file: {blend}")
    with blend.open("rb") as f:
        head = f.read(12)
    # Blender files start with "BLENDER" (uncompressed), or are gzip / zstd compressed.
    if not (head.startswith(b"BLENDER") or head.startswith(b"\x1f\x8b") or head.startswith(b"\x28\xb5\x2f\xfd")):
        raise DatasetError(f"--blend: not a .blend file: {blend}")


def _open_blend(bpy, blend: Path) -> None:
    try:
        bpy.ops.wm.open_mainfile(filepath=str(blend.resolve()), load_ui=False)
    except RuntimeError as exc:
        lines = [line for line in str(exc).strip().splitlines() if line.strip()]
        raise DatasetError(f"--blend: Blender cannot open {blend}: {lines[-1] if lines else 'unknown error'}") from exc


def _renderable_objects(scene) -> list:
    return [ob for ob in scene.objects if ob.type in RENDERABLE_TYPES and not ob.hide_render]


def _scene_bounds(bpy, scene, objects):
    """World-space bounding box (min, max) of the evaluated renderable objects, or None."""
    from mathutils import Vector  # noqa: PLC0415

    depsgraph = bpy.context.evaluated_depsgraph_get()
    corners = []
    for ob in objects:
        ev = ob.evaluated_get(depsgraph)
        corners.extend(ev.matrix_world @ Vector(c) for c in ev.bound_box)
    if not corners:
        return None
    a = np.array([tuple(c) for c in corners])
    return a.min(axis=0), a.max(axis=0)


@contextlib.contextmanager
def _saved_attributes(pairs):
    """Restore (owner, attribute) values on exit: make_dataset(blend=None) leaves the scene as it found it."""
    saved = []
    for owner, name in pairs:
        with contextlib.suppress(AttributeError, TypeError):
            saved.append((owner, name, getattr(owner, name)))
    try:
        yield
    finally:
        for owner, name, value in reversed(saved):
            with contextlib.suppress(AttributeError, TypeError, ValueError):
                setattr(owner, name, value)


def _configure_render(scene, opts: Options) -> None:
    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = opts.samples
    scene.cycles.use_denoising = opts.denoise
    scene.cycles.seed = opts.seed
    # A box filter one pixel wide averages each pixel's own area, centred on the
    # pixel centre that the NeRF's ray goes through.
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    render.film_transparent = not opts.opaque
    render.resolution_x, render.resolution_y = opts.resolution
    render.resolution_percentage = 100
    render.pixel_aspect_x, render.pixel_aspect_y = (opts.pixel_aspect, 1.0) if opts.pixel_aspect >= 1 else (1.0, 1.0 / opts.pixel_aspect)
    render.use_border = False
    # The dataset is the film itself: no compositor or sequencer strips (they may drop alpha
    # or change the look), no stereo views, no motion blur, only the active view layer.
    render.use_compositing = False
    render.use_sequencer = False
    render.use_multiview = False
    render.use_motion_blur = False
    render.use_single_layer = True
    render.use_persistent_data = True  # keep the BVH between views: only the camera moves
    render.threads_mode = "AUTO" if opts.threads == 0 else "FIXED"
    if opts.threads:
        render.threads = opts.threads
    settings = render.image_settings
    settings.file_format = "PNG"
    settings.color_mode = "RGB" if opts.opaque else "RGBA"
    settings.color_depth = "8"
    settings.compression = 15
    if opts.view_transform != "KEEP":
        try:
            scene.view_settings.view_transform = opts.view_transform
        except TypeError as exc:
            raise DatasetError(f"--view-transform: Blender has no view transform {opts.view_transform!r}") from exc
        scene.view_settings.look = "None"
        scene.view_settings.exposure = 0.0
        scene.view_settings.gamma = 1.0
        scene.view_settings.use_curve_mapping = False


def _render_settings_to_restore(scene):
    r, c, v, s = scene.render, getattr(scene, "cycles", None), scene.view_settings, scene.render.image_settings
    pairs = [(scene, "camera")]
    pairs += [(r, n) for n in ("engine", "film_transparent", "resolution_x", "resolution_y", "resolution_percentage",
                              "pixel_aspect_x", "pixel_aspect_y", "use_border", "use_persistent_data",
                              "use_compositing", "use_sequencer", "use_multiview", "use_motion_blur",
                              "use_single_layer",
                              "threads_mode", "threads")]
    if c is not None:
        pairs += [(c, n) for n in ("device", "samples", "use_denoising", "seed", "pixel_filter_type", "filter_width")]
    pairs += [(v, n) for n in ("view_transform", "look", "exposure", "gamma", "use_curve_mapping")]
    pairs += [(s, n) for n in ("file_format", "color_mode", "color_depth", "compression")]
    return pairs


@contextlib.contextmanager
def _quiet_stdout(enabled: bool):
    """Silence Blender's own C-level prints during a render (our progress lines stay readable)."""
    if not enabled:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _render_views(bpy, scene, cam_obj, positions, target, out_dir: Path, opts: Options, label: str,
                  progress, quiet: bool) -> list[dict]:
    from mathutils import Matrix, Vector  # noqa: PLC0415

    images = out_dir / "images"
    images.mkdir(parents=True, exist_ok=True)
    frames = []
    target_v = Vector(target)
    for k, pos in enumerate(positions):
        pos_v = Vector(tuple(float(x) for x in pos))
        rotation = (target_v - pos_v).to_track_quat("-Z", "Y")
        cam_obj.matrix_world = Matrix.Translation(pos_v) @ rotation.to_matrix().to_4x4()
        bpy.context.view_layer.update()
        matrix = [list(map(float, row)) for row in cam_obj.matrix_world]  # what Blender renders with
        name = f"{opts.frame_prefix}{k}.png"
        final = images / name
        partial = images / f".{name}.partial.png"
        started = time.perf_counter()
        try:
            with _quiet_stdout(quiet):
                bpy.ops.render.render(write_still=False)
                bpy.data.images["Render Result"].save_render(filepath=str(partial), scene=scene)
        except RuntimeError as exc:
            with contextlib.suppress(FileNotFoundError):
                partial.unlink()
            lines = [line for line in str(exc).strip().splitlines() if line.strip()]
            raise DatasetError(f"Blender failed to render view {k} ({final}): "
                               f"{lines[-1] if lines else 'unknown error'}") from exc
        if not partial.is_file():
            raise DatasetError(f"Blender rendered view {k} but wrote no image to {partial}")
        os.replace(partial, final)
        frames.append({"file_path": f"images/{name}", "transform_matrix": matrix})
        if progress:
            progress(f"[{label} {k + 1:>{len(str(len(positions)))}}/{len(positions)}] {final}  "
                     f"{time.perf_counter() - started:.2f} s")
    return frames


def make_dataset(out, blend=None, progress=print, quiet: bool = True, **options) -> dict:
    """Render the dataset of `blend` (a .blend path; None: the scene loaded now) into `out`.

    Keyword options are the fields of `Options` (count, radius, resolution=(w, h) or w,
    seed, target, hemisphere, min_elevation, layout, samples, denoise, test_count, opaque, aabb, lens, sensor_width,
    sensor_height, sensor_fit, shift, pixel_aspect, view_transform, threads, ...).
    `progress` gets one line per view (None: silent). Raises DatasetError for bad input.
    Returns {"transforms": Path, "test_transforms": Path or None, "frames": int, "seconds": float}.
    """
    resolution = options.pop("resolution", Options.resolution)
    if isinstance(resolution, int):
        resolution = (resolution, resolution)
    unknown = set(options) - set(Options.__dataclass_fields__)
    if unknown:
        raise TypeError(f"make_dataset() got unknown options: {', '.join(sorted(unknown))}")
    opts = Options(resolution=tuple(resolution), **options)
    opts.target = tuple(float(v) for v in opts.target)
    opts.shift = tuple(float(v) for v in opts.shift)
    opts.validate()

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out: exists and is not a folder: {out}")

    if blend is not None:
        blend = Path(blend)
        _check_blend_file(blend)
    bpy = _import_bpy()
    started = time.perf_counter()
    if blend is not None:
        _open_blend(bpy, blend)
    scene = bpy.context.scene
    previous_frame = scene.frame_current
    if opts.frame is not None:
        scene.frame_set(opts.frame)
    try:
        return _make(bpy, scene, out, blend, opts, progress, quiet, started)
    finally:
        if blend is None and opts.frame is not None:
            scene.frame_set(previous_frame)


def _make(bpy, scene, out: Path, blend, opts: Options, progress, quiet: bool, started: float) -> dict:
    objects = _renderable_objects(scene)
    where = f"{blend}" if blend is not None else "the loaded scene"
    if not objects:
        raise DatasetError(f"--blend: {where} has no objects to render in scene {scene.name!r} "
                           f"(no visible mesh, curve, text, volume or point cloud)")
    bounds = _scene_bounds(bpy, scene, objects)
    far = 1000.0
    if bounds is not None:
        lo, hi = bounds
        target = np.asarray(opts.target)
        extent = float(np.max(np.abs(np.stack([lo - target, hi - target]))) * math.sqrt(3.0))
        far = max(100.0, 2.0 * (opts.radius + extent))
        inside = np.all(lo - 1e-9 <= target) and np.all(target <= hi + 1e-9)
        # (An opaque capture inside a room has its cameras inside the scene's box on purpose.)
        if opts.radius < extent and progress and inside and not opts.opaque:
            progress(f"warning: --radius {opts.radius} may put cameras inside the scene "
                     f"(objects reach {extent:.3g} from the target)")

    out.mkdir(parents=True, exist_ok=True)
    # A folder being re-rendered must not keep describing the old views while its images change:
    # the old transforms.json goes first, the new one is written (atomically) once every view is done.
    for stale in (out / "transforms.json", out / "test" / "transforms.json"):
        with contextlib.suppress(FileNotFoundError):
            stale.unlink()
    cam_data = bpy.data.cameras.new(CAMERA_NAME)
    cam_obj = bpy.data.objects.new(CAMERA_NAME, cam_data)
    scene.collection.objects.link(cam_obj)
    try:
        with _saved_attributes(_render_settings_to_restore(scene) if blend is None else []):
            cam_data.type = "PERSP"
            cam_data.lens_unit = "MILLIMETERS"
            cam_data.lens = opts.lens
            cam_data.sensor_width = opts.sensor_width
            cam_data.sensor_height = opts.sensor_height
            cam_data.sensor_fit = opts.sensor_fit
            cam_data.shift_x, cam_data.shift_y = opts.shift
            cam_data.clip_start = 0.01
            cam_data.clip_end = far
            cam_data.dof.use_dof = False
            scene.camera = cam_obj
            _configure_render(scene, opts)

            intr = intrinsics(scene, cam_obj)
            generator = {
                "tool": "tools/make_dataset.py",
                "blend": str(blend) if blend is not None else None,
                "blender": bpy.app.version_string,
                "engine": "CYCLES", "device": "CPU",
                "view_transform": scene.view_settings.view_transform,
                "alpha": "none (opaque film, RGB images: the background is part of the capture)"
                         if opts.opaque else "straight",
                "pixel_centres": "ray of pixel (i, j) = ((i + 0.5 - cx) / fl_x, -(j + 0.5 - cy) / fl_y, -1)",
                **{k: v for k, v in asdict(opts).items() if k not in ("extras",)},
                **opts.extras,
            }
            generator["lens"], generator["sensor_fit"], generator["shift"] = cam_data.lens, cam_data.sensor_fit, list(opts.shift)

            box = {} if opts.aabb is None else {"aabb": [list(map(float, c)) for c in opts.aabb]}
            positions = camera_positions(opts.count, opts.radius, opts.target, opts.hemisphere, opts.seed, opts.layout,
                                         opts.min_elevation)
            frames = _render_views(bpy, scene, cam_obj, positions, opts.target, out, opts, "train", progress, quiet)
            transforms = out / "transforms.json"
            write_json_atomic(transforms, {**intr, **box, "frames": frames, "generator": {**generator, "split": "train"}})

            test_transforms = None
            if opts.test_count:
                # Other views than the training ones: uniform random, from a different stream of the seed.
                test_positions = camera_positions(opts.test_count, opts.radius, opts.target, opts.hemisphere,
                                                  opts.seed + 1_000_003, "random", opts.min_elevation)
                test_dir = out / "test"
                test_frames = _render_views(bpy, scene, cam_obj, test_positions, opts.target, test_dir, opts,
                                            "test", progress, quiet)
                test_transforms = test_dir / "transforms.json"
                write_json_atomic(test_transforms, {**intr, **box, "frames": test_frames,
                                                    "generator": {**generator, "split": "test"}})
    finally:
        bpy.data.objects.remove(cam_obj)
        bpy.data.cameras.remove(cam_data)

    seconds = time.perf_counter() - started
    if progress:
        total = opts.count + opts.test_count
        progress(f"wrote {transforms} ({total} views, {opts.resolution[0]}x{opts.resolution[1]}, {seconds:.1f} s)")
    return {"transforms": transforms, "test_transforms": test_transforms, "frames": opts.count, "seconds": seconds}


# --------------------------------------------------------------------------- command line


def build_parser() -> argparse.ArgumentParser:
    d = Options()
    p = argparse.ArgumentParser(
        prog="make_dataset.py",
        description="Render a NeRF dataset (transforms.json + RGBA PNGs, straight alpha; RGB with --opaque) "
                    "from a .blend, headless, "
                    "with Cycles on the CPU. Cameras on a sphere around --target, looking at it.")
    p.add_argument("--blend", required=True, type=Path, help="the .blend to render (its active scene)")
    p.add_argument("--out", required=True, type=Path, help="output folder (transforms.json, images/, test/)")
    p.add_argument("--count", type=int, default=d.count, help=f"training views (default {d.count})")
    p.add_argument("--radius", type=float, default=d.radius, help=f"camera distance from the target (default {d.radius})")
    p.add_argument("--resolution", type=int, nargs="+", metavar=("W", "H"), default=list(d.resolution),
                   help="image size in pixels: W [H] (default 200; H defaults to W)")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the camera layout and of Cycles (default 0)")
    p.add_argument("--target", type=float, nargs=3, metavar=("X", "Y", "Z"), default=list(d.target),
                   help="point the cameras look at (default 0 0 0)")
    p.add_argument("--hemisphere", action="store_true", help="upper (+Z) hemisphere only (default: whole sphere)")
    p.add_argument("--min-elevation", type=float, default=None, metavar="DEG",
                   help="cameras from this elevation (degrees above the target's horizontal plane) up to the "
                        "zenith, e.g. -15: the upper hemisphere and a little below (default: whole sphere)")
    p.add_argument("--layout", choices=("spiral", "random"), default=d.layout,
                   help="spiral: even Fibonacci spiral turned by the seed (default); random: uniform random")
    p.add_argument("--samples", type=int, default=d.samples, help=f"Cycles samples per pixel (default {d.samples})")
    p.add_argument("--denoise", action="store_true", help="Cycles denoising (OpenImageDenoise; default off)")
    p.add_argument("--test-count", type=int, default=d.test_count,
                   help="extra random views written to OUT/test/ (default 0: none)")
    p.add_argument("--opaque", action="store_true",
                   help="no transparent film: RGB images, the background (a room) is part of the capture")
    p.add_argument("--aabb", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"), default=None,
                   help="write this box as transforms.json's \"aabb\" (the region the object lies in)")
    p.add_argument("--lens", type=float, default=d.lens, help=f"focal length in mm (default {d.lens})")
    p.add_argument("--sensor-width", type=float, default=d.sensor_width, help=f"mm (default {d.sensor_width})")
    p.add_argument("--sensor-height", type=float, default=d.sensor_height,
                   help=f"mm, used by --sensor-fit VERTICAL (default {d.sensor_height})")
    p.add_argument("--sensor-fit", choices=SENSOR_FITS, default=d.sensor_fit, help="Blender's sensor fit (default AUTO)")
    p.add_argument("--shift", type=float, nargs=2, metavar=("X", "Y"), default=list(d.shift),
                   help="Blender's lens shift, in units of the fitted side (default 0 0)")
    p.add_argument("--pixel-aspect", type=float, default=d.pixel_aspect,
                   help="pixel width / pixel height (default 1)")
    p.add_argument("--view-transform", default=d.view_transform,
                   help="colour management view transform (default Standard; KEEP: the .blend's own)")
    p.add_argument("--frame", type=int, default=None, help="scene frame to render (default: the .blend's current)")
    p.add_argument("--threads", type=int, default=d.threads, help="render threads (default 0: all cores)")
    p.add_argument("--verbose", action="store_true", help="let Blender print its own render messages")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if len(args.resolution) not in (1, 2):
        print(f"error: --resolution takes W or W H, got {len(args.resolution)} numbers", file=sys.stderr)
        return 2
    resolution = tuple(args.resolution) * (2 if len(args.resolution) == 1 else 1)
    try:
        make_dataset(
            args.out, blend=args.blend, quiet=not args.verbose,
            progress=lambda line: print(line, flush=True),
            count=args.count, radius=args.radius, resolution=resolution, seed=args.seed, target=tuple(args.target),
            hemisphere=args.hemisphere, min_elevation=args.min_elevation, layout=args.layout, samples=args.samples, denoise=args.denoise,
            test_count=args.test_count, lens=args.lens, sensor_width=args.sensor_width,
            sensor_height=args.sensor_height, sensor_fit=args.sensor_fit, shift=tuple(args.shift),
            pixel_aspect=args.pixel_aspect, view_transform=args.view_transform, threads=args.threads,
            frame=args.frame, opaque=args.opaque,
            aabb=None if args.aabb is None else (tuple(args.aabb[:3]), tuple(args.aabb[3:])))
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
