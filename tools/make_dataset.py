#!/usr/bin/env python3
"""Render a NeRF dataset (transforms.json + RGBA PNGs) from any .blend, headless.

What BlenderNeRF does for instant-ngp users, from the command line and with
the `bpy` module (Blender as a Python module), no Blender UI:

    python tools/make_dataset.py --blend SCENE.blend --out DIR \
        [--count 100] [--radius 4] [--resolution 200 [200]] [--seed 0] \
        [--hemisphere | --min-elevation DEG] [--samples 16] [--test-count 0] \
        [--engine CYCLES|KEEP] \
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

What is written (DIR/transforms.json, DIR/images/, and with --test-count N > 0 DIR/test/ for
`engine eval --data DIR/test`), its keys and its camera convention (Blender's own camera-to-world
matrices; pixel centres; fl_x/fl_y/cx/cy exact with --shift and --pixel-aspect): the docstring of
`blender_nerf_deform/addon/capture/dataset.py`, which writes it.

With --engine KEEP the .blend's own render engine and sampling settings render the views
(only resolution, film transparency, output format and colour view are set, and the compositor,
sequencer, border, stereo and motion blur are off); --samples and --denoise then do not apply.

Importable: `make_dataset(...)` does the same as the command line and returns
the paths it wrote. It loads the .blend into this process's Blender (the
`bpy` module is one process-wide Blender), replacing what was loaded; with
`blend=None` it renders the scene already loaded (its camera is added and
removed again, and the render settings it changes are restored).

This file is the command line only: the capture itself lives in the add-on,
`blender_nerf_deform/addon/capture/dataset.py`, which the add-on's Capture Dataset
operator runs too (one code for both); its public names are re-exported here.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# The capture core is the add-on's, in the package at the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from blender_nerf_deform.addon.capture.dataset import (  # noqa: E402,F401  (re-exported: tools import them from here)
    BUILTIN_ENGINES,
    CAMERA_NAME,
    ENGINES,
    GOLDEN_ANGLE,
    RENDERABLE_TYPES,
    SENSOR_FITS,
    DatasetError,
    Options,
    camera_positions,
    intrinsics,
    make_dataset,
    project,
    renderable,
    selection_frame,
    write_json_atomic,
)

# --------------------------------------------------------------------------- command line


def build_parser() -> argparse.ArgumentParser:
    d = Options()
    p = argparse.ArgumentParser(
        prog="make_dataset.py",
        description="Render a NeRF dataset (transforms.json + RGBA PNGs, straight alpha; RGB with --opaque) "
        "from a .blend, headless, "
        "with Cycles on the CPU. Cameras on a sphere around --target, looking at it.",
    )
    p.add_argument("--blend", required=True, type=Path, help="the .blend to render (its active scene)")
    p.add_argument("--out", required=True, type=Path, help="output folder (transforms.json, images/, test/)")
    p.add_argument("--count", type=int, default=d.count, help=f"training views (default {d.count})")
    p.add_argument(
        "--radius", type=float, default=d.radius, help=f"camera distance from the target (default {d.radius})"
    )
    p.add_argument(
        "--resolution",
        type=int,
        nargs="+",
        metavar=("W", "H"),
        default=list(d.resolution),
        help="image size in pixels: W [H] (default 200; H defaults to W)",
    )
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the camera layout and of Cycles (default 0)")
    p.add_argument(
        "--target",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        default=list(d.target),
        help="point the cameras look at (default 0 0 0)",
    )
    p.add_argument("--hemisphere", action="store_true", help="upper (+Z) hemisphere only (default: whole sphere)")
    p.add_argument(
        "--min-elevation",
        type=float,
        default=None,
        metavar="DEG",
        help="cameras from this elevation (degrees above the target's horizontal plane) up to the "
        "zenith, e.g. -15: the upper hemisphere and a little below (default: whole sphere)",
    )
    p.add_argument(
        "--layout",
        choices=("spiral", "random"),
        default=d.layout,
        help="spiral: even Fibonacci spiral turned by the seed (default); random: uniform random",
    )
    p.add_argument(
        "--engine",
        choices=ENGINES,
        default=d.engine,
        help="CYCLES: Cycles on the CPU with --samples (default); KEEP: the .blend's own render engine "
        "and its sampling settings",
    )
    p.add_argument("--samples", type=int, default=d.samples, help=f"Cycles samples per pixel (default {d.samples})")
    p.add_argument("--denoise", action="store_true", help="Cycles denoising (OpenImageDenoise; default off)")
    p.add_argument(
        "--test-count", type=int, default=d.test_count, help="extra random views written to OUT/test/ (default 0: none)"
    )
    p.add_argument(
        "--opaque",
        action="store_true",
        help="no transparent film: RGB images, the background (a room) is part of the capture",
    )
    p.add_argument(
        "--aabb",
        type=float,
        nargs=6,
        metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
        default=None,
        help='write this box as transforms.json\'s "aabb" (the region the object lies in)',
    )
    p.add_argument("--lens", type=float, default=d.lens, help=f"focal length in mm (default {d.lens})")
    p.add_argument("--sensor-width", type=float, default=d.sensor_width, help=f"mm (default {d.sensor_width})")
    p.add_argument(
        "--sensor-height",
        type=float,
        default=d.sensor_height,
        help=f"mm, used by --sensor-fit VERTICAL (default {d.sensor_height})",
    )
    p.add_argument(
        "--sensor-fit", choices=SENSOR_FITS, default=d.sensor_fit, help="Blender's sensor fit (default AUTO)"
    )
    p.add_argument(
        "--shift",
        type=float,
        nargs=2,
        metavar=("X", "Y"),
        default=list(d.shift),
        help="Blender's lens shift, in units of the fitted side (default 0 0)",
    )
    p.add_argument("--pixel-aspect", type=float, default=d.pixel_aspect, help="pixel width / pixel height (default 1)")
    p.add_argument(
        "--view-transform",
        default=d.view_transform,
        help="colour management view transform (default Standard; KEEP: the .blend's own)",
    )
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
            args.out,
            blend=args.blend,
            quiet=not args.verbose,
            progress=lambda line: print(line, flush=True),
            count=args.count,
            radius=args.radius,
            resolution=resolution,
            seed=args.seed,
            target=tuple(args.target),
            hemisphere=args.hemisphere,
            min_elevation=args.min_elevation,
            layout=args.layout,
            engine=args.engine,
            samples=args.samples,
            denoise=args.denoise,
            test_count=args.test_count,
            lens=args.lens,
            sensor_width=args.sensor_width,
            sensor_height=args.sensor_height,
            sensor_fit=args.sensor_fit,
            shift=tuple(args.shift),
            pixel_aspect=args.pixel_aspect,
            view_transform=args.view_transform,
            threads=args.threads,
            frame=args.frame,
            opaque=args.opaque,
            aabb=None if args.aabb is None else (tuple(args.aabb[:3]), tuple(args.aabb[3:])),
        )
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    from blender_nerf_deform.engine.errors import run_command  # an error nobody foresaw: one line naming its log

    raise SystemExit(run_command("make_dataset.py", main))
