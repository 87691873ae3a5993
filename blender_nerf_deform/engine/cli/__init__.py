"""`python -m blender_nerf_deform.engine <command>`: the engine's command line.

A public interface (docs/ARCHITECTURE.md): scripts, render farms and the project's own
benchmarks call it, so the commands and options below stay stable. One module
per command (cli/<command>.py) turns the parsed options into calls of the
stage functions, the same ones the worker serves; it is imported only when its
command runs, so that `--help` never loads torch. Bad input is one `error:` line
and exit status 2; an error nobody foresaw is one `error:` line too (exit 1),
naming the log file that holds its traceback.
"""

from __future__ import annotations

import argparse
import importlib

from ..errors import EngineError, run_command
from ..logs import log_to_stderr

PROG = "python -m blender_nerf_deform.engine"
DATA_HELP = (
    "dataset: a transforms.json (instant-ngp, nerfstudio or NeRF-synthetic) or its folder; an LLFF folder "
    "(poses_bounds.npy + images_N/; --downscale N picks images_N) or one of its image folders; a COLMAP "
    "sparse model (cameras, images, points3D .bin/.txt) or a folder with sparse/0/ and images/"
)


def _command(module: str):
    """Handler that runs `cli/<module>.py`'s main(args), imported only when the command runs."""

    def handler(args: argparse.Namespace) -> int:
        return importlib.import_module(f"{__package__}.{module}").main(args)

    return handler


def _substeps_argument(p: argparse.ArgumentParser) -> None:
    from ..nerf.substeps import FINAL_SUBSTEPS, MAX_SUBSTEPS, check_substeps

    def substeps(text: str) -> int:  # the renderer's own check, so the two bounds cannot drift apart
        try:
            return check_substeps(int(text))
        except (ValueError, EngineError) as exc:
            raise argparse.ArgumentTypeError(
                str(exc) if isinstance(exc, EngineError) else f"{text!r} is not an integer"
            ) from None

    p.add_argument(
        "--substeps",
        type=substeps,
        default=FINAL_SUBSTEPS,
        metavar="S",
        help=f"samples per step of the NeRF's march (1 to {MAX_SUBSTEPS}): more is finer and slower; "
        f"default {FINAL_SUBSTEPS}, the quality of final frames; 1 the speed of previews",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Train a NeRF, extract its mesh, build a tetrahedral cage, and render "
        "it undeformed or ray-bent by a deformed cage. No Blender needed.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("train", help="train a NeRF on a dataset (transforms.json, LLFF, COLMAP)")
    p.add_argument("--data", required=True, metavar="PATH", help=DATA_HELP)
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder; the checkpoint is RUN_DIR/nerf.ckpt")
    p.add_argument("--max-seconds", type=float, metavar="S", help="stop training after S seconds")
    p.add_argument("--steps", type=int, metavar="N", help="stop training after N steps")
    p.add_argument(
        "--seed", type=int, default=0, metavar="N", help="seed of the initial weights and the ray sampling (default 0)"
    )
    p.add_argument(
        "--device", choices=("auto", "cpu", "cuda"), default="auto", help="default: cuda if available, else cpu"
    )
    p.add_argument("--downscale", type=int, default=1, metavar="K", help="box-filter the images by an integer factor K")
    p.add_argument(
        "--scene",
        choices=("auto", "bounded", "unbounded"),
        default="auto",
        help="bounded: the NeRF lives in the dataset's box (objects on transparent backgrounds); unbounded: "
        "an inner box plus a contracted background for photos with a room or sky behind the object; "
        "auto (default): unbounded for photos without alpha",
    )
    p.add_argument(
        "--masks",
        choices=("auto", "object", "ignore"),
        default="auto",
        help="what the frames' masks (`mask_path`) mean: object: the object alone is real, outside the "
        "mask is empty space (a NeRF of the object, transparent around it: turntable and product "
        "captures); ignore: the masked-out pixels are not trained (passers-by), the rest of the "
        "photo is; auto (default): object when the masks keep a shape inside the photo, ignore when "
        "they keep most of it. The choice is printed",
    )
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/nerf.ckpt when it exists")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace RUN_DIR/nerf.ckpt when it exists "
        "(without --resume or --overwrite an existing checkpoint is an error)",
    )
    p.add_argument(
        "--checkpoint-every",
        type=float,
        default=120.0,
        metavar="S",
        help="rewrite the checkpoint every S seconds (default 120)",
    )
    p.add_argument(
        "--drop-blurry",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="leave out that fraction of the frames, the blurriest (by instant-ngp's per-frame `sharpness`, "
        "else measured on the images); default 0: keep all",
    )
    p.set_defaults(handler=_command("train"))

    p = sub.add_parser("eval", help="print PSNR of a checkpoint over a dataset's frames")
    p.add_argument("--nerf", required=True, metavar="CKPT", help="checkpoint written by `train`")
    p.add_argument("--data", required=True, metavar="PATH", help=DATA_HELP)
    p.add_argument("--downscale", type=int, default=1, metavar="K", help="box-filter the images by an integer factor K")
    _substeps_argument(p)
    p.add_argument(
        "--device", choices=("auto", "cpu", "cuda"), default="auto", help="default: cuda if available, else cpu"
    )
    p.set_defaults(handler=_command("eval"))

    p = sub.add_parser("render", help="render frames of a NeRF, optionally ray-bent by a deformed cage")
    p.add_argument("--nerf", required=True, metavar="CKPT", help="checkpoint written by `train`")
    p.add_argument(
        "--cameras",
        required=True,
        metavar="TRANSFORMS_JSON",
        help="cameras to render: a transforms.json, or any dataset form --data of train reads",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="writes DIR/<name>.png (RGBA, straight alpha) per frame")
    p.add_argument("--cage", metavar="CAGE.npz", help="rest cage written by `cage`")
    p.add_argument(
        "--deformed",
        metavar="V.npy|DIR",
        help="(N,3) deformed positions of the cage's vertices, same order; "
        "or a folder of such .npy poses, one per frame of --cameras, matched in natural name order",
    )
    p.add_argument("--downscale", type=int, default=1, metavar="K", help="render at 1/K of the cameras' resolution")
    _substeps_argument(p)
    p.add_argument(
        "--device", choices=("auto", "cpu", "cuda"), default="auto", help="default: cuda if available, else cpu"
    )
    p.set_defaults(handler=_command("render"))

    p = sub.add_parser(
        "bake-volume",
        help="sample the NeRF, at rest or ray-bent by a deformed cage, on a voxel grid "
        "(.npz per pose; tools/vdb_from_npz.py makes OpenVDB files of them)",
    )
    p.add_argument("--nerf", required=True, metavar="CKPT", help="checkpoint written by `train`")
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="writes DIR/<pose name>.npz per pose (DIR/rest.npz without "
        "a cage): voxel indices, density per NeRF unit, colour (sRGB), the index->NeRF matrix",
    )
    p.add_argument("--cage", metavar="CAGE.npz", help="rest cage written by `cage`")
    p.add_argument(
        "--deformed",
        metavar="V.npy|DIR",
        help="(N,3) deformed positions of the cage's vertices, same order; "
        "or a folder of such .npy poses, one volume each",
    )
    p.add_argument(
        "--region",
        metavar="REGION.json",
        help="bake only this oriented box (an edit region, the NeRF's frame; the grid's axes follow it)",
    )
    p.add_argument(
        "--extent",
        choices=("nerf", "cage"),
        help="bake the NeRF's box (default; an unbounded NeRF's inner box) or the box of the cage as posed",
    )
    p.add_argument(
        "--resolution",
        type=int,
        default=256,
        metavar="R",
        help="voxels along the box's longest side (cubic voxels; default 256)",
    )
    p.add_argument(
        "--supersample",
        type=int,
        default=1,
        metavar="S",
        help="S^3 points averaged per voxel (default 1: the voxel's centre)",
    )
    p.add_argument(
        "--device", choices=("auto", "cpu", "cuda"), default="auto", help="default: cuda if available, else cpu"
    )
    p.set_defaults(handler=_command("bake_volume"))

    p = sub.add_parser("extract", help="extract a filtered surface mesh from a NeRF's density")
    p.add_argument("--nerf", required=True, metavar="CKPT", help="checkpoint written by `train`")
    p.add_argument("--out", required=True, metavar="MESH.ply", help="output mesh with vertex colours")
    p.add_argument("--threshold", type=float, metavar="T", help="density threshold of the surface (default 10)")
    p.add_argument("--resolution", type=int, metavar="R", help="grid resolution per axis (default 256)")
    p.add_argument(
        "--min-volume",
        type=float,
        metavar="V",
        help="drop connected components smaller than V "
        "(world units cubed; default: 1%% of the largest component's volume)",
    )
    p.add_argument("--decimate", type=int, metavar="FACES", help="decimate the filtered mesh to about FACES faces")
    p.add_argument(
        "--region",
        metavar="REGION.json",
        action="append",
        help="extract only inside this oriented box "
        '({"center": [x,y,z], "size": [sx,sy,sz], "rotation_euler": [rx,ry,rz]}, radians, XYZ, the NeRF\'s '
        "frame): the resolution is spent there and the surface is closed where the box cuts the scene; "
        "repeat it for several objects (one surface each, `nerf_part` in the PLY; one cage each)",
    )
    p.add_argument(
        "--pick",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="keep only the part of the surface "
        "connected to this point on the object (grown over the density grid, within the region)",
    )
    p.add_argument(
        "--device", choices=("auto", "cpu", "cuda"), default="auto", help="default: cuda if available, else cpu"
    )
    p.set_defaults(handler=_command("extract"))

    p = sub.add_parser("cage", help="build the tetrahedral cage around an extracted mesh, once")
    p.add_argument("--nerf", required=True, metavar="CKPT", help="checkpoint written by `train`")
    p.add_argument("--mesh", required=True, metavar="MESH.ply", help="mesh written by `extract`")
    p.add_argument("--out", required=True, metavar="CAGE.npz", help="cage: `vertices` (N,3) and `tets` (M,4)")
    p.add_argument(
        "--margin",
        type=float,
        metavar="M",
        help="distance from the object to the cage's boundary, world units "
        "(default 3%% of the mesh's diagonal; widened where the NeRF's density is still soft there)",
    )
    p.add_argument("--edge-length", type=float, metavar="L", help="target tet edge length, world units")
    p.add_argument(
        "--target-tets", type=int, metavar="N", help="approximate number of tets (ignored with --edge-length)"
    )
    p.add_argument(
        "--refine-edge",
        type=float,
        metavar="L",
        help="then refine (longest-edge bisection) every tet whose "
        "longest edge exceeds L, within --refine-box: where a pose will stretch or bend sharply (a smooth "
        "stretch across a band narrower than a few tets smears with a coarse cage)",
    )
    p.add_argument(
        "--refine-box",
        type=float,
        nargs=6,
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help="where --refine-edge applies (tets whose centroid is inside; default: the whole cage)",
    )
    p.add_argument(
        "--threshold", type=float, metavar="T", help="surface density threshold used for extraction (default 10)"
    )
    p.add_argument(
        "--region",
        metavar="REGION.json",
        help="the edit region the mesh was extracted in: recorded in the "
        "cage, and where the mesh has no cut flags its vertices on the region's boundary are the cut",
    )
    p.add_argument(
        "--no-pin-cut",
        action="store_true",
        help="do not pin the cage where the region cut the scene "
        "(by default the deformation fades to nothing there, so the object stays attached)",
    )
    p.set_defaults(handler=_command("cage"))

    p = sub.add_parser("prepare", help="photos with no poses -> a transforms.json dataset, by structure from motion")
    p.add_argument("--images", required=True, metavar="DIR", help="folder of photos (.jpg/.png) of one capture")
    p.add_argument("--out", required=True, metavar="DATASET_DIR", help="new folder: transforms.json + images/")
    p.add_argument(
        "--matcher",
        choices=("exhaustive", "sequential"),
        default="exhaustive",
        help="exhaustive (any order; default) or sequential (video frames, many photos)",
    )
    p.add_argument(
        "--max-size", type=int, default=1600, metavar="PX", help="longest side for feature extraction (default 1600)"
    )
    p.add_argument("--seed", type=int, default=0, metavar="N", help="seed of COLMAP's random choices (default 0)")
    p.add_argument(
        "--colmap-log",
        action="store_true",
        help="print COLMAP's whole log (every photo, match and adjustment); by default its warnings only",
    )
    p.set_defaults(handler=_command("prepare"))

    p = sub.add_parser(
        "compile",
        help="compile the CPU kernels once, so the first train or render on this machine "
        "does not wait for them (numba's cache: NUMBA_CACHE_DIR, else beside the sources)",
    )
    p.set_defaults(handler=_command("compile"))

    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    log_to_stderr()  # the stages' log lines ("read ...", warnings) on stderr, as they always were
    return run_command(args.command, lambda: args.handler(args))
