"""Render a NeRF dataset (transforms.json + RGBA PNGs) from a Blender scene: the one capture core.

Two front ends share this module, so a dataset made from the UI and one made from the command
line are made by the same code:

- `tools/make_dataset.py`: the command line (any .blend, headless, with the `bpy` module),
  a thin argparse over `make_dataset()`; it re-exports this module's public names.
- Capture Dataset (`capture/operators.py`, `nerf_deform.capture_dataset`): the add-on's operator.
  It saves a copy of the current file to a temporary .blend, and a separate Blender process
  (`capture/runner.py`: `blender -b --factory-startup TMP.blend --python runner.py`,
  or the Python of the `bpy` module) opens it and calls `make_dataset()` here, so Blender's UI
  stays usable while it renders.

bpy and numpy only, relative imports only (the add-on runs as `bl_ext.<repo>.blender_nerf_deform`
as well as `blender_nerf_deform`), and bpy is imported only when rendering.

Cameras sit on a sphere (or the upper hemisphere, +Z up; or the part of the sphere above
`min_elevation` degrees) of the given radius around the target point and look at it. Each view
is rendered over a transparent film and saved as an 8-bit RGBA PNG with straight (unassociated)
alpha: background alpha 0, opaque surfaces alpha 1. With `opaque` the film is not transparent
and the views are 8-bit RGB PNGs (no alpha channel): what is behind the object (a room,
tools/make_room_scene.py) is part of the capture, as in a real photograph, and the cameras may
stand inside the scene. The view transform is "Standard" unless `view_transform` says otherwise
(Blender 5's default AgX would tint colours); a .blend on disk is never modified.

The render engine (`engine`):

- "CYCLES" (the command line's default): Cycles on the CPU with `samples` samples, denoising
  off unless `denoise`, the seed of the layout, and a one-pixel box pixel filter, so a pixel is
  the average over its own area, centred where the NeRF's ray goes. Why Cycles on the CPU: it
  needs no GPU or display. With the bpy module headless (Blender 5.0.1, no GPU), Workbench
  renders through a software EGL context (with EGL errors printed) and EEVEE compiles its
  shaders for far longer than a small view takes to render, while Cycles renders such a view
  at once and is deterministic for a given seed.
- "KEEP" (Capture Dataset's default): the scene's own engine and its sampling settings
  (samples, denoising, pixel filter, device). Only what makes a view a dataset image is set:
  resolution (100 %, the pixel aspect), film transparency, the output format (PNG, RGBA or
  RGB, 8 bit) and the colour view; and in both modes what would make the written image differ
  from the film the camera model describes is switched off: render border, compositor,
  sequencer, stereo views, motion blur (and only the active view layer is rendered).

What is written (the NeRF-synthetic / instant-ngp form, read by the engine):

    DIR/transforms.json        training views
    DIR/images/r_<k>.png
    DIR/test/transforms.json   only with test_count N > 0: N other random
    DIR/test/images/r_<k>.png  views, so that `engine eval --data DIR/test` works

transforms.json keys:
    camera_angle_x, camera_angle_y   field of view in radians (x: horizontal)
    fl_x, fl_y, cx, cy               focal lengths and principal point, pixels
    w, h                             image size, pixels
    frames[]: file_path              relative to the json's folder, extension included
              transform_matrix       camera-to-world 4x4: Blender's own
                                     `matrix_world` of the camera that rendered
                                     the view (no axis change)
    aabb                             only with `aabb`: [[x0, y0, z0], [x1, y1, z1]], the
                                     box the object lies in (the engine's scene bounds)
    generator                        how the views were made (tool, options)

Camera convention (docs/ARCHITECTURE.md, Conventions): the camera looks down its local -Z with +Y up;
pixel (i, j) (column i, row j counted from the top of the image) is the ray

    d_camera = ((i + 0.5 - cx) / fl_x,  -(j + 0.5 - cy) / fl_y,  -1)

through the pixel centre. Without lens shift and with square pixels,
cx = w/2, cy = h/2 and fl_x = fl_y = 0.5 * w / tan(0.5 * camera_angle_x), so a
reader that only knows `camera_angle_x` gets the same rays. With `shift` or
`pixel_aspect` only the fl_x/fl_y/cx/cy form is exact.

`make_dataset(...)` returns the paths it wrote. It loads the .blend into this process's Blender
(the `bpy` module is one process-wide Blender), replacing what was loaded; with `blend=None` it
renders the scene already loaded (its camera is added and removed again, and the render
settings it changes are restored). `selection_frame(...)` is the target, automatic radius and
box that Capture Dataset derives from the selected objects.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
RENDERABLE_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT", "VOLUME", "POINTCLOUD", "CURVES", "GREASEPENCIL"}
SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")
CAMERA_NAME = "make_dataset_camera"
ENGINES = ("CYCLES", "KEEP")  # Cycles on the CPU; the scene's own engine and sampling settings
# The engines a factory-started background Blender has (EEVEE's id is BLENDER_EEVEE_NEXT in 4.2-4.4).
BUILTIN_ENGINES = ("CYCLES", "BLENDER_EEVEE", "BLENDER_EEVEE_NEXT", "BLENDER_WORKBENCH")


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
    min_elevation: float | None = (
        None  # degrees; cameras from this elevation up to the zenith (None: sphere / hemisphere)
    )
    layout: str = "spiral"  # "spiral": even Fibonacci spiral, turned by the seed; "random": uniform random
    engine: str = "CYCLES"  # "CYCLES": Cycles on the CPU with `samples`; "KEEP": the scene's engine and sampling
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
                raise DatasetError(
                    "--hemisphere and --min-elevation exclude each other (--hemisphere is --min-elevation 0)"
                )
            if not (math.isfinite(self.min_elevation) and -90.0 <= self.min_elevation < 90.0):
                raise DatasetError(f"--min-elevation must be in [-90, 90) degrees, got {self.min_elevation!r}")
        if self.aabb is not None:
            lo, hi = (tuple(map(float, c)) for c in self.aabb)
            if (
                len(lo) != 3
                or len(hi) != 3
                or not all(map(math.isfinite, lo + hi))
                or not all(a < b for a, b in zip(lo, hi))
            ):
                raise DatasetError(
                    f"--aabb must be six finite numbers X0 Y0 Z0 X1 Y1 Z1 with X0 < X1, Y0 < Y1, "
                    f"Z0 < Z1, got {self.aabb!r}"
                )
        if self.engine not in ENGINES:
            raise DatasetError(f"--engine must be one of {', '.join(ENGINES)}, got {self.engine!r}")
        if self.layout not in ("spiral", "random"):
            raise DatasetError(f"--layout must be spiral or random, got {self.layout!r}")
        if self.frame is not None and not isinstance(self.frame, int):
            raise DatasetError(f"--frame must be a whole number, got {self.frame!r}")
        if not isinstance(self.threads, int) or self.threads < 0:
            raise DatasetError(f"--threads must be a whole number >= 0 (0: all cores), got {self.threads!r}")
        if not self.frame_prefix or any(c in self.frame_prefix for c in "/\\"):
            raise DatasetError(f"frame prefix must be a non-empty file-name part, got {self.frame_prefix!r}")


# --------------------------------------------------------------------------- geometry (no bpy)


def camera_positions(
    count: int,
    radius: float,
    target=(0.0, 0.0, 0.0),
    hemisphere: bool = False,
    seed: int = 0,
    layout: str = "spiral",
    min_elevation: float | None = None,
) -> np.ndarray:
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
    from ..data.camera import pinhole_from_blender  # noqa: PLC0415

    pin = pinhole_from_blender(scene, cam_obj)
    return {
        "fl_x": pin.fx,
        "fl_y": pin.fy,
        "cx": pin.cx,
        "cy": pin.cy,
        "w": pin.width,
        "h": pin.height,
        "camera_angle_x": 2.0 * math.atan(0.5 * pin.width / pin.fx),
        "camera_angle_y": 2.0 * math.atan(0.5 * pin.height / pin.fy),
    }


def project(points, transform_matrix, fl_x, fl_y, cx, cy) -> np.ndarray:
    """Continuous pixel coordinates (x right, y down; pixel (i, j) spans [i, i+1) x [j, j+1)) of world points."""
    c2w = np.asarray(transform_matrix, dtype=np.float64)
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    cam = (np.linalg.inv(c2w) @ np.c_[p, np.ones(len(p))].T).T[:, :3]
    depth = -cam[:, 2]
    return np.stack([cx + fl_x * cam[:, 0] / depth, cy - fl_y * cam[:, 1] / depth], axis=1)


# --------------------------------------------------------------------------- files


def write_json_atomic(path, data) -> None:
    """Write `data` as JSON to a temporary file beside `path`, then rename it over `path`: a reader
    (or a crash) never sees a half-written file. Raises DatasetError naming the file."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise DatasetError(f"cannot write {path}: {exc.strerror or exc}") from exc
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(json.dumps(data, indent=1) + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise DatasetError(f"cannot write {path}: {exc.strerror or exc}") from exc


def _process_umask() -> int:
    mask = os.umask(0o022)  # read by setting it, once: files get the permissions open() would give
    os.umask(mask)
    return mask


_UMASK = _process_umask()


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


def renderable(objects) -> list:
    """The objects among `objects` that render (meshes, curves, text, volumes, ...; not hidden from render)."""
    return [ob for ob in objects if ob.type in RENDERABLE_TYPES and not ob.hide_render]


# How far the cameras stand by default: the selection's bounding sphere spans this fraction of
# the narrower side of the picture; and the box written as "aabb" is the selection's bounds
# grown by this fraction of its largest side on every side.
FILL = 0.8
AABB_PAD = 0.05


def selection_frame(
    bpy,
    objects,
    resolution=(200, 200),
    lens: float = 50.0,
    sensor_width: float = 36.0,
    fill: float = FILL,
    pad: float = AABB_PAD,
) -> dict:
    """Where to aim at `objects` (renderable, evaluated, world space): {"bounds": (lo, hi),
    "target": the centre of their bounding box, "radius": the distance at which their bounding
    sphere spans `fill` of the narrower side of a `resolution` picture through a `lens` mm lens on
    a `sensor_width` mm sensor (AUTO fit, square pixels), "aabb": the bounds grown by `pad` of
    their largest side}. Raises DatasetError when nothing in `objects` renders."""
    objects = renderable(objects)
    bounds = _scene_bounds(bpy, None, objects) if objects else None
    if bounds is None:
        raise DatasetError(
            "none of the selected objects renders (select a mesh, curve, text, volume or point cloud "
            "that is not hidden from render)"
        )
    lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    centre = 0.5 * (lo + hi)
    extent = hi - lo
    sphere = max(0.5 * float(np.linalg.norm(extent)), 1e-3)
    w, h = resolution
    focal_px = lens / sensor_width * max(w, h)  # AUTO sensor fit: the sensor spans the larger side
    half_angle = math.atan(0.5 * min(w, h) / focal_px)
    radius = sphere / (fill * math.sin(half_angle))
    grow = pad * max(float(extent.max()), 1e-3)
    return {
        "bounds": (tuple(map(float, lo)), tuple(map(float, hi))),
        "target": tuple(map(float, centre)),
        "radius": float(radius),
        "aabb": (tuple(map(float, lo - grow)), tuple(map(float, hi + grow))),
    }


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
    if opts.engine == "CYCLES":
        render.engine = "CYCLES"
        scene.cycles.device = "CPU"
        scene.cycles.samples = opts.samples
        scene.cycles.use_denoising = opts.denoise
        scene.cycles.seed = opts.seed
        # A box filter one pixel wide averages each pixel's own area, centred on the
        # pixel centre that the NeRF's ray goes through.
        scene.cycles.pixel_filter_type = "BOX"
        scene.cycles.filter_width = 1.0
    # "KEEP": the scene's engine, samples, denoising, pixel filter and device as they are.
    render.film_transparent = not opts.opaque
    render.resolution_x, render.resolution_y = opts.resolution
    render.resolution_percentage = 100
    render.pixel_aspect_x, render.pixel_aspect_y = (
        (opts.pixel_aspect, 1.0) if opts.pixel_aspect >= 1 else (1.0, 1.0 / opts.pixel_aspect)
    )
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
    pairs += [
        (r, n)
        for n in (
            "engine",
            "film_transparent",
            "resolution_x",
            "resolution_y",
            "resolution_percentage",
            "pixel_aspect_x",
            "pixel_aspect_y",
            "use_border",
            "use_persistent_data",
            "use_compositing",
            "use_sequencer",
            "use_multiview",
            "use_motion_blur",
            "use_single_layer",
            "threads_mode",
            "threads",
        )
    ]
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


def _render_views(
    bpy,
    scene,
    cam_obj,
    positions,
    target,
    out_dir: Path,
    opts: Options,
    label: str,
    progress,
    quiet: bool,
    on_view=None,
    done_before: int = 0,
    total: int = 0,
) -> list[dict]:
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
            raise DatasetError(
                f"Blender failed to render view {k} ({final}): {lines[-1] if lines else 'unknown error'}"
            ) from exc
        if not partial.is_file():
            raise DatasetError(f"Blender rendered view {k} but wrote no image to {partial}")
        os.replace(partial, final)
        frames.append({"file_path": f"images/{name}", "transform_matrix": matrix})
        seconds = time.perf_counter() - started
        if progress:
            progress(f"[{label} {k + 1:>{len(str(len(positions)))}}/{len(positions)}] {final}  {seconds:.2f} s")
        if on_view:
            on_view(done_before + k + 1, total or len(positions), label, str(final), seconds)
    return frames


def make_dataset(out, blend=None, progress=print, quiet: bool = True, on_view=None, **options) -> dict:
    """Render the dataset of `blend` (a .blend path; None: the scene loaded now) into `out`.

    Keyword options are the fields of `Options` (count, radius, resolution=(w, h) or w,
    seed, target, hemisphere, min_elevation, layout, engine, samples, denoise, test_count, opaque, aabb, lens,
    sensor_width, sensor_height, sensor_fit, shift, pixel_aspect, view_transform, threads, ...).
    `progress` gets one line per view (None: silent); `on_view(done, total, split, path, seconds)`
    is called after each view (training and test views counted together). Raises DatasetError
    for bad input.
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
        return _make(bpy, scene, out, blend, opts, progress, quiet, started, on_view)
    finally:
        if blend is None and opts.frame is not None:
            scene.frame_set(previous_frame)


def _make(bpy, scene, out: Path, blend, opts: Options, progress, quiet: bool, started: float, on_view=None) -> dict:
    objects = _renderable_objects(scene)
    where = f"{blend}" if blend is not None else "the loaded scene"
    if not objects:
        raise DatasetError(
            f"--blend: {where} has no objects to render in scene {scene.name!r} "
            f"(no visible mesh, curve, text, volume or point cloud)"
        )
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
            progress(
                f"warning: --radius {opts.radius} may put cameras inside the scene "
                f"(objects reach {extent:.3g} from the target)"
            )

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
                "device": getattr(getattr(scene, "cycles", None), "device", None)
                if scene.render.engine == "CYCLES"
                else None,
                "view_transform": scene.view_settings.view_transform,
                "alpha": "none (opaque film, RGB images: the background is part of the capture)"
                if opts.opaque
                else "straight",
                "pixel_centres": "ray of pixel (i, j) = ((i + 0.5 - cx) / fl_x, -(j + 0.5 - cy) / fl_y, -1)",
                **{k: v for k, v in asdict(opts).items() if k not in ("extras",)},
                **opts.extras,
            }
            generator["lens"], generator["sensor_fit"], generator["shift"] = (
                cam_data.lens,
                cam_data.sensor_fit,
                list(opts.shift),
            )
            # The engine that rendered (the option's "KEEP" names no engine), and the option itself.
            generator["engine"], generator["engine_option"] = scene.render.engine, opts.engine
            if opts.engine == "KEEP" and scene.render.engine == "CYCLES":
                generator["samples"], generator["denoise"] = scene.cycles.samples, scene.cycles.use_denoising

            box = {} if opts.aabb is None else {"aabb": [list(map(float, c)) for c in opts.aabb]}
            positions = camera_positions(
                opts.count, opts.radius, opts.target, opts.hemisphere, opts.seed, opts.layout, opts.min_elevation
            )
            total = opts.count + opts.test_count
            frames = _render_views(
                bpy, scene, cam_obj, positions, opts.target, out, opts, "train", progress, quiet, on_view, 0, total
            )
            transforms = out / "transforms.json"
            write_json_atomic(
                transforms, {**intr, **box, "frames": frames, "generator": {**generator, "split": "train"}}
            )

            test_transforms = None
            if opts.test_count:
                # Other views than the training ones: uniform random, from a different stream of the seed.
                test_positions = camera_positions(
                    opts.test_count,
                    opts.radius,
                    opts.target,
                    opts.hemisphere,
                    opts.seed + 1_000_003,
                    "random",
                    opts.min_elevation,
                )
                test_dir = out / "test"
                test_frames = _render_views(
                    bpy,
                    scene,
                    cam_obj,
                    test_positions,
                    opts.target,
                    test_dir,
                    opts,
                    "test",
                    progress,
                    quiet,
                    on_view,
                    opts.count,
                    total,
                )
                test_transforms = test_dir / "transforms.json"
                write_json_atomic(
                    test_transforms, {**intr, **box, "frames": test_frames, "generator": {**generator, "split": "test"}}
                )
    finally:
        bpy.data.objects.remove(cam_obj)
        bpy.data.cameras.remove(cam_data)

    seconds = time.perf_counter() - started
    if progress:
        progress(f"wrote {transforms} ({total} views, {opts.resolution[0]}x{opts.resolution[1]}, {seconds:.1f} s)")
    return {"transforms": transforms, "test_transforms": test_transforms, "frames": opts.count, "seconds": seconds}
