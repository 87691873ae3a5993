#!/usr/bin/env python3
"""Benchmark (issue 5): ray-bent NeRF renders against Cycles ground truth of known smooth deformations.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/bending_groundtruth.py \\
        --work /work/runs/gt_bench [--train-seconds 240] [--views 100] [--test-views 10] \\
        [--resolution 128] [--train-resolution 128] [--samples 32] [--edge-length L] [--margin M]
        [--refine-edge L] [--maps a,b] [--train-steps N] [--reuse]

What it does, end to end, as a user would:

1. Builds a scene in Blender through `bpy`: a "bar" (a box 0.6 x 0.36 x 1.4,
   faces subdivided to 0.05) and, above it across a 0.45 gap, a "head" (a box
   0.4 x 0.4 x 0.3) - the part that moves on its own. Every surface is an
   emission-only material whose colour comes from the UV map (a checker of a
   hue ramp along the height against a second ramp around the perimeter), so
   the appearance is fixed to the surface and moves with it.
2. Renders the rest pose with `tools/make_dataset.py` (Cycles, CPU, transparent
   film, 8-bit RGBA with straight alpha): training views on a sphere of radius 4
   and random test views.
3. For each known smooth map of 3D points (MAPS below: non-uniform scale, bend,
   twist, moving the head, and the strong stretches and compressions of issue 18:
   widening 1.3x in x and y, pulling the ends apart so that a band of the bar
   stretches to 2.7x its height (3.55x at its middle), squashing to 0.5x in x),
   moves the meshes' vertices by the map and renders the
   SAME test cameras again with `make_dataset` (same seed and count, so the
   same random test cameras; checked).
4. Trains the NeRF on the rest-pose training set (`engine train`), extracts a
   mesh (`engine extract`), builds the cage once (`engine cage`), applies each
   map to the cage vertices (V.npy) and renders the test cameras through the
   cage (`engine render --cage --deformed`); the rest pose is rendered with no
   cage, and once more through the cage with V = rest vertices (identity).
5. Scores: PSNR of every render against its Cycles ground truth, both
   composited on white (straight-alpha RGB over white), averaged over the test
   views. Target (issue 5): every deformation within 1.5 dB of the rest-pose
   PSNR. Exit status 1 when a target is missed.

The "moving one part" map translates points by w(z) * t, with w a smoothstep
from 0 to 1 across the middle of the gap between bar and head (z in
[0.575, 0.675]). On the object's surfaces w is exactly 0 (bar) or 1 (head), so
the ground truth is a rigid move of the head; in the cage, which is one
connected envelope (the default --margin 0.3 is wider than half the gap), the
tets across the gap stretch smoothly. A map applied to the cage equals the map
applied to the surface only where it is affine over each tet: the script reports
that geometric error directly (each ground-truth mesh vertex embedded in the rest
cage and carried by the deformed cage, against the exact map; in world units
and in pixels at the test cameras' distance), so a missed target can be told
apart from a NeRF limitation.

A smooth stretch across a band narrower than a few tets is where the cage's
piecewise-affine map is furthest from the exact one (issue 18: 4 px on the
stretch map with the default cage, and 2.7 dB of its PSNR). `--refine-edge L`
builds the cage as a user who will stretch there would: `cage --refine-edge L
--refine-box` over the stretch band (REFINE_BOX), every other tet as built.

A map that magnifies (widen, stretch) shows the NeRF closer than any training view did: a NeRF
learnt from 128 px views seen 1.3x closer draws its soft edges 1.3x wider, whatever bends it
(issue 18 measured 3.1 dB lost by the rest scene seen from 1.3x closer, no cage at all).
`--train-resolution R` renders the training views at R px (same cameras, same field of view)
while the test views and their ground truth stay at --resolution, so the NeRF has the detail a
magnified view asks for and the figures measure the bending rather than that floor.

Other diagnostic columns: alpha PSNR (silhouette agreement), the PSNR of the
UNdeformed NeRF render against the deformed ground truth (how much each map
changes the image), inverted tets, render wall time per map (process start and
cage preparation included; the speed figure of issue 5 is another benchmark).

Large outputs stay in --work (datasets, run, renders, logs, results.json).
`--reuse` keeps the ground truth, checkpoint, mesh and cage already in --work
(the script says which) and redoes the NeRF renders and scores.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

TARGET_DB = 1.5

# --------------------------------------------------------------------------- the scene (world frame, Z up)

BAR = ((-0.30, -0.18, -1.00), (0.30, 0.18, 0.40))
HEAD = ((-0.20, -0.20, 0.85), (0.20, 0.20, 1.15))
EDGE = 0.05  # subdivision of every face of the ground-truth meshes (world units)
Z_LO, Z_HI = BAR[0][2], HEAD[1][2]
HEIGHT = Z_HI - Z_LO
Z_MID = 0.5 * (Z_LO + Z_HI)  # centre of the bend and the twist
GAP_FALLOFF = (0.575, 0.675)  # where "move the head" blends from 0 to 1: the middle of the gap 0.40 .. 0.85
CHECKER_SIZE = 0.15  # world units per checker square (about 6 pixels at 128 px)

# --------------------------------------------------------------------------- the maps (functions of points)


def scale_map(p: np.ndarray) -> np.ndarray:
    """Non-uniform scale about the origin: x 1.3, y 0.8, z 0.9."""
    return p * np.array([1.3, 0.8, 0.9])


BEND_RATE = 0.5  # rad per world unit along z: +-0.54 rad at the ends


def bend_map(p: np.ndarray) -> np.ndarray:
    """Bend the whole height around an axis parallel to Y at x = 1 / BEND_RATE (an arc of constant curvature)."""
    r = 1.0 / BEND_RATE
    theta = BEND_RATE * (p[:, 2] - Z_MID)
    lever = r - p[:, 0]
    out = p.copy()
    out[:, 0] = r - lever * np.cos(theta)
    out[:, 2] = Z_MID + lever * np.sin(theta)
    return out


TWIST_RATE = 0.8  # rad per world unit along z: +-0.86 rad at the ends


def twist_map(p: np.ndarray) -> np.ndarray:
    """Twist about the Z axis: rotation angle proportional to height."""
    phi = TWIST_RATE * (p[:, 2] - Z_MID)
    c, s = np.cos(phi), np.sin(phi)
    out = p.copy()
    out[:, 0] = c * p[:, 0] - s * p[:, 1]
    out[:, 1] = s * p[:, 0] + c * p[:, 1]
    return out


HEAD_MOVE = np.array([0.35, -0.10, 0.10])


def move_head_map(p: np.ndarray) -> np.ndarray:
    """Translate the head by HEAD_MOVE; weight = smoothstep across the middle of the gap (0 on the bar, 1 on the
    head)."""
    a, b = GAP_FALLOFF
    s = np.clip((p[:, 2] - a) / (b - a), 0.0, 1.0)
    w = s * s * (3.0 - 2.0 * s)
    return p + w[:, None] * HEAD_MOVE


WIDEN = np.array([1.3, 1.3, 1.0])


def widen_map(p: np.ndarray) -> np.ndarray:
    """Uniform widening 1.3x in both horizontal axes about the Z axis (every side face stretched across its normal)."""
    return p * WIDEN


STRETCH_BAND = (-0.30, 0.00)  # a band of the bar itself (the bar spans z -1.00 .. 0.40)
STRETCH_LIFT = 0.51  # the band's 0.30 grows to 0.81: 2.7x its height on average, 3.55x at its middle


def stretch_weight(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smoothstep across STRETCH_BAND and its derivative dw/dz."""
    a, b = STRETCH_BAND
    s = np.clip((z - a) / (b - a), 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s), np.where((s > 0) & (s < 1), 6.0 * s * (1.0 - s) / (b - a), 0.0)


def stretch_map(p: np.ndarray) -> np.ndarray:
    """Pull the two ends of the object apart along z (each by half STRETCH_LIFT); the band between them,
    a part of the bar's own surface, stretches smoothly (smoothstep) to 2.7x its height (3.55x at its middle)."""
    w, _ = stretch_weight(p[:, 2])
    out = p.copy()
    out[:, 2] = p[:, 2] + (w - 0.5) * STRETCH_LIFT
    return out


# Where --refine-edge refines the cage: the stretch band, 0.15 above and below, across the whole cage.
REFINE_BOX = ((-5.0, -5.0, STRETCH_BAND[0] - 0.15), (5.0, 5.0, STRETCH_BAND[1] + 0.15))

SQUASH = np.array([0.5, 1.0, 1.0])


def squash_map(p: np.ndarray) -> np.ndarray:
    """Squash to 0.5x along x (the +-x faces compressed across their normal, the +-y faces along them)."""
    return p * SQUASH


MAPS = {
    "scale": scale_map,
    "bend": bend_map,
    "twist": twist_map,
    "move_head": move_head_map,
    "widen": widen_map,
    "stretch": stretch_map,
    "squash": squash_map,
}

# --------------------------------------------------------------------------- Blender


def _perimeter_u(co, normal, lo, hi) -> float:
    """Distance around the box's side (world units) of a point on a side face, from the -X,-Y corner."""
    (x0, y0, _), (x1, y1, _) = lo, hi
    w, d = x1 - x0, y1 - y0
    nx, ny = normal[0], normal[1]
    if ny < -0.5:  # -Y side, walking +X
        return co[0] - x0
    if nx > 0.5:  # +X side, walking +Y
        return w + co[1] - y0
    if ny > 0.5:  # +Y side, walking -X
        return w + d + x1 - co[0]
    return 2 * w + d + y1 - co[1]  # -X side, walking -Y


def _box_object(bpy, name, bounds, material):
    """A closed box mesh, faces subdivided to about EDGE, with a UV map tied to the surface."""
    from default_scene import closed_box_bmesh, object_from_bmesh  # noqa: PLC0415

    lo, hi = bounds
    (x0, y0, _), (x1, y1, _) = lo, hi
    dx, dy = x1 - x0, y1 - y0
    bm = closed_box_bmesh(bounds, tuple(max(1, round((hi[i] - lo[i]) / EDGE)) for i in range(3)))
    uv = bm.loops.layers.uv.new("UVMap")
    perimeter = 2 * (dx + dy)
    for face in bm.faces:
        n = tuple(face.normal)
        for loop in face.loops:
            co = tuple(loop.vert.co)
            if abs(n[2]) > 0.5:  # caps: their own patch of UV space, v near the cap's height
                u = (perimeter + 0.5 + co[0] - x0) / HEIGHT
                v = (co[2] - Z_LO + co[1] - y0) / HEIGHT
            else:
                u = _perimeter_u(co, n, lo, hi) / HEIGHT
                v = (co[2] - Z_LO) / HEIGHT
            loop[uv].uv = (u, v)
    return object_from_bmesh(bpy, name, bm, material)


def _uv_material(bpy):
    """Emission only (strength 1): checker of a hue ramp along v against a light/dark ramp along u."""
    from default_scene import empty_node_material  # noqa: PLC0415

    mat, nodes, links = empty_node_material(bpy, "GroundTruthUV")
    uv = nodes.new("ShaderNodeUVMap")
    uv.uv_map = "UVMap"
    sep = nodes.new("ShaderNodeSeparateXYZ")
    links.new(uv.outputs["UV"], sep.inputs["Vector"])
    hue = nodes.new("ShaderNodeValToRGB")
    stops = (
        (0.0, (0.80, 0.04, 0.03)),
        (0.25, (0.90, 0.40, 0.02)),
        (0.5, (0.45, 0.75, 0.04)),
        (0.75, (0.03, 0.45, 0.80)),
        (1.0, (0.50, 0.08, 0.75)),
    )
    _set_ramp(hue.color_ramp, stops)
    links.new(sep.outputs["Y"], hue.inputs["Fac"])
    around = nodes.new("ShaderNodeMath")
    around.operation = "MULTIPLY"
    around.inputs[1].default_value = 0.45  # sides' u spans about 0 .. 2.2 (perimeter / height)
    links.new(sep.outputs["X"], around.inputs[0])
    tone = nodes.new("ShaderNodeValToRGB")
    _set_ramp(
        tone.color_ramp,
        ((0.0, (0.92, 0.92, 0.85)), (0.35, (0.12, 0.12, 0.16)), (0.7, (0.90, 0.60, 0.75)), (1.0, (0.30, 0.22, 0.10))),
    )
    links.new(around.outputs["Value"], tone.inputs["Fac"])
    checker = nodes.new("ShaderNodeTexChecker")
    checker.inputs["Scale"].default_value = HEIGHT / CHECKER_SIZE
    links.new(uv.outputs["UV"], checker.inputs["Vector"])
    links.new(hue.outputs["Color"], checker.inputs["Color1"])
    links.new(tone.outputs["Color"], checker.inputs["Color2"])
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Strength"].default_value = 1.0
    links.new(checker.outputs["Color"], emission.inputs["Color"])
    output = nodes.new("ShaderNodeOutputMaterial")
    output.target = "ALL"
    links.new(emission.outputs["Emission"], output.inputs["Surface"])
    return mat


def _set_ramp(ramp, stops):
    elements = ramp.elements
    while len(elements) < len(stops):
        elements.new(0.5)
    for element, (pos, rgb) in zip(elements, stops):
        element.position = pos
        element.color = (*rgb, 1.0)


def build_scene(bpy) -> list:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    material = _uv_material(bpy)
    objects = [_box_object(bpy, "Bar", BAR, material), _box_object(bpy, "Head", HEAD, material)]
    world = bpy.data.worlds.new("Black")
    if world.node_tree is None:
        world.use_nodes = True
    background = world.node_tree.nodes.get("Background")
    if background is not None:
        background.inputs["Strength"].default_value = 0.0
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.max_bounces = 0  # emission seen directly
    return objects


def _vertices(obj) -> np.ndarray:
    co = np.empty(len(obj.data.vertices) * 3, dtype=np.float64)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _set_vertices(bpy, obj, co: np.ndarray) -> None:
    obj.data.vertices.foreach_set("co", np.asarray(co, dtype=np.float64).ravel())
    obj.data.update()
    bpy.context.view_layer.update()


def render_ground_truth(work: Path, args, maps=None, rest_pose: bool = True) -> dict:
    """Rest-pose dataset (train + test) and, per map of `maps` (default all), the deformed meshes seen
    from the same test cameras. rest_pose False: only the maps (the rest pose's dataset is kept)."""
    import bpy  # noqa: PLC0415

    from make_dataset import make_dataset  # noqa: PLC0415

    objects = build_scene(bpy)
    rest = {obj.name: _vertices(obj) for obj in objects}
    common = dict(
        radius=4.0,
        resolution=(args.resolution, args.resolution),
        samples=args.samples,
        seed=args.seed,
        test_count=args.test_views,
        threads=0,
        denoise=False,
    )
    t0 = time.perf_counter()
    if rest_pose:
        train_res = args.train_resolution
        make_dataset(
            work / "data",
            blend=None,
            progress=None,
            count=args.views,
            **{**common, "resolution": (train_res, train_res)},
        )
        print(
            f"ground truth: rest pose, {args.views} training + {args.test_views} test views, {train_res} px "
            f"({time.perf_counter() - t0:.1f} s)",
            flush=True,
        )
        if train_res != args.resolution:  # the rest pose's test views at the scoring resolution
            t0 = time.perf_counter()
            make_dataset(work / "gt_rest", blend=None, progress=None, count=1, **common)
            print(
                f"ground truth: rest pose, {args.test_views} test views, {args.resolution} px "
                f"({time.perf_counter() - t0:.1f} s)",
                flush=True,
            )
    for name in MAPS if maps is None else maps:
        fn = MAPS[name]
        t0 = time.perf_counter()
        for obj in objects:
            _set_vertices(bpy, obj, fn(rest[obj.name]))
        # make_dataset always renders training views: one here, unused; the test views are
        # drawn from (seed, test_count) only, so they are the rest pose's test cameras.
        make_dataset(work / f"gt_{name}", blend=None, progress=None, count=1, **common)
        print(f"ground truth: {name}, {args.test_views} test views ({time.perf_counter() - t0:.1f} s)", flush=True)
    for obj in objects:
        _set_vertices(bpy, obj, rest[obj.name])
    surface = np.concatenate([rest[o.name] for o in objects])
    np.save(work / "gt_surface_vertices.npy", surface)
    return {"surface_vertices": len(surface)}


def rest_test_json(work: Path, args) -> Path:
    """The rest pose's test views at the scoring resolution."""
    if args.train_resolution != args.resolution:
        return work / "gt_rest" / "test" / "transforms.json"
    return work / "data" / "test" / "transforms.json"


# --------------------------------------------------------------------------- engine command line


def engine(log: Path, *argv) -> float:
    """Run `python -m blender_nerf_deform.engine ARGV`, output to `log`; seconds taken. Raises on failure."""
    cmd = [sys.executable, "-m", "blender_nerf_deform.engine", *map(str, argv)]
    t0 = time.perf_counter()
    with log.open("w") as f:
        f.write(" ".join(cmd) + "\n")
        f.flush()
        rc = subprocess.run(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT).returncode
    seconds = time.perf_counter() - t0
    if rc != 0:
        tail = log.read_text()[-3000:]
        raise SystemExit(f"engine {argv[0]} failed (exit {rc}); log {log}:\n{tail}")
    return seconds


def _last_lines(log: Path, n: int = 1, contains: str = "") -> str:
    lines = [ln.strip() for ln in log.read_text().replace("\r", "\n").splitlines() if ln.strip() and contains in ln]
    return " | ".join(lines[-n:])


# --------------------------------------------------------------------------- scoring


def _load_rgba(path: Path) -> np.ndarray:
    from PIL import Image  # noqa: PLC0415

    with Image.open(path) as im:
        return np.asarray(im.convert("RGBA"), dtype=np.float64) / 255.0


def _on_white(rgba: np.ndarray) -> np.ndarray:
    a = rgba[..., 3:]
    return rgba[..., :3] * a + (1.0 - a)


def score(render_dir: Path, gt_transforms: Path) -> dict:
    """Mean PSNR (RGB on white) and alpha PSNR of DIR/<name>.png against the frames of a transforms.json."""
    from blender_nerf_deform.engine.nerf.evaluate import psnr  # noqa: PLC0415

    meta = json.loads(gt_transforms.read_text())
    rgb, alpha = [], []
    for frame in meta["frames"]:
        gt = _load_rgba(gt_transforms.parent / frame["file_path"])
        out = _load_rgba(render_dir / f"{Path(frame['file_path']).stem}.png")
        if out.shape != gt.shape:
            raise SystemExit(f"{render_dir}: frame {frame['file_path']} is {out.shape}, ground truth {gt.shape}")
        rgb.append(psnr(_on_white(out), _on_white(gt)))
        alpha.append(psnr(out[..., 3], gt[..., 3]))
    return {"psnr": float(np.mean(rgb)), "psnr_alpha": float(np.mean(alpha)), "per_view": rgb}


def cage_map_error(surface: np.ndarray, rest_vertices, tets, fn, px_per_unit: float) -> dict:
    """How far the cage's piecewise-affine version of `fn` puts the true surface from where `fn` puts it."""
    from blender_nerf_deform.engine.geometry.embedding import embed_points  # noqa: PLC0415

    emb = embed_points(surface, rest_vertices, tets)
    err = np.linalg.norm(emb.apply(fn(rest_vertices)) - fn(surface), axis=1)
    return {
        "mean": float(err.mean()),
        "max": float(err.max()),
        "mean_px": float(err.mean() * px_per_unit),
        "max_px": float(err.max() * px_per_unit),
        "outside": emb.n_outside,
    }


def cage_components(tets: np.ndarray, n_vertices: int) -> int:
    """Connected pieces of the cage (tets sharing a vertex)."""
    from scipy.sparse import coo_matrix  # noqa: PLC0415
    from scipy.sparse.csgraph import connected_components  # noqa: PLC0415

    edges = tets[:, [0, 0, 0]].ravel(), tets[:, [1, 2, 3]].ravel()
    graph = coo_matrix((np.ones(len(edges[0])), edges), shape=(n_vertices, n_vertices))
    _, label = connected_components(graph, directed=False)
    return len(np.unique(label[np.unique(tets)]))


# --------------------------------------------------------------------------- main


def _select_maps(ap, names: str | None) -> dict:
    if not names:
        return dict(MAPS)
    chosen = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in chosen if n not in MAPS]
    if unknown or not chosen:
        ap.error(f"--maps: unknown map(s) {', '.join(unknown) or '(none given)'}; known: {', '.join(MAPS)}")
    return {n: MAPS[n] for n in chosen}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/work/runs/gt_bench"), help="output folder (outside the repo)")
    ap.add_argument("--views", type=int, default=100, help="training views (default 100)")
    ap.add_argument("--test-views", type=int, default=10, help="test views (default 10)")
    ap.add_argument("--resolution", type=int, default=128, help="image side in pixels (default 128)")
    ap.add_argument(
        "--train-resolution",
        type=int,
        default=None,
        help="training views' side in pixels (default: --resolution); test views stay at --resolution",
    )
    ap.add_argument("--samples", type=int, default=32, help="Cycles samples per pixel (default 32, no denoiser)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-seconds", type=float, default=240.0, help="NeRF training budget (default 240)")
    ap.add_argument(
        "--train-steps",
        type=int,
        default=None,
        help="train for this many steps instead of --train-seconds (repeatable: the tests use it)",
    )
    ap.add_argument("--maps", default=None, help=f"comma-separated subset of the maps (default all: {','.join(MAPS)})")
    ap.add_argument(
        "--margin",
        type=float,
        default=0.3,
        help="cage margin (default 0.3: wider than half the 0.45 gap, so the cage is one piece)",
    )
    ap.add_argument("--edge-length", type=float, default=None, help="cage tet edge length (default: the engine's)")
    ap.add_argument(
        "--refine-edge",
        type=float,
        default=None,
        help="refine the cage (`cage --refine-edge L --refine-box ...`) to longest edges <= L where the "
        "stretch map stretches (REFINE_BOX: its band, 0.15 either side), as a user who will stretch "
        "there would (default: no refinement)",
    )
    ap.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="device of training, extraction and renders (default: cuda if available, else cpu)",
    )
    ap.add_argument(
        "--reuse",
        action="store_true",
        help="keep ground truth, checkpoint, mesh and cage already in --work; redo renders and scores",
    )
    args = ap.parse_args(argv)
    for flag, value in (("--resolution", args.resolution), ("--train-resolution", args.train_resolution)):
        if value is not None and value < 1:
            ap.error(f"{flag} must be a whole number of pixels >= 1, got {value}")
    args.train_resolution = args.train_resolution or args.resolution  # resolved once: everything reads it
    maps = _select_maps(ap, args.maps)
    work = args.work.resolve()
    if str(work).startswith(str(REPO) + "/"):
        print("note: --work is inside the repository; outputs are large", flush=True)
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    reused = []

    # 1-3. Ground truth.
    test_json = rest_test_json(work, args)
    have_rest = (work / "data" / "transforms.json").is_file() and test_json.is_file()
    if have_rest and args.reuse:  # a --work made at other resolutions is not this benchmark
        train_w = json.loads((work / "data" / "transforms.json").read_text()).get("w")
        test_w = json.loads(test_json.read_text()).get("w")
        if (train_w, test_w) != (args.train_resolution, args.resolution):
            raise SystemExit(
                f"--reuse: {work} holds {train_w} px training / {test_w} px test views, not "
                f"{args.train_resolution} / {args.resolution}: use another --work"
            )
    missing = [m for m in maps if not (work / f"gt_{m}" / "test" / "transforms.json").is_file()]
    if args.reuse and have_rest and not missing:
        reused.append("ground truth")
    elif args.reuse and have_rest:  # maps added since: render only theirs (the test cameras are checked below)
        reused.append("ground truth of the rest pose and of " + ", ".join(m for m in maps if m not in missing))
        render_ground_truth(work, args, maps=missing, rest_pose=False)
    else:
        render_ground_truth(work, args, maps=list(maps))
    rest_meta = json.loads(test_json.read_text())
    for m in maps:  # the deformed ground truth must be seen from the rest pose's test cameras
        meta = json.loads((work / f"gt_{m}" / "test" / "transforms.json").read_text())
        a = np.array([f["transform_matrix"] for f in meta["frames"]])
        b = np.array([f["transform_matrix"] for f in rest_meta["frames"]])
        if a.shape != b.shape or not np.allclose(a, b, atol=1e-9) or meta["fl_x"] != rest_meta["fl_x"]:
            raise SystemExit(f"gt_{m}: test cameras differ from the rest pose's")
    px_per_unit = rest_meta["fl_x"] / 4.0  # at the cameras' distance from the origin (radius 4)

    # 4. NeRF, mesh, cage.
    run = work / "run"
    run.mkdir(exist_ok=True)
    ckpt, mesh, cage_path = run / "nerf.ckpt", run / "mesh.ply", run / "cage.npz"
    timings = {}
    if args.reuse and ckpt.is_file():
        reused.append("checkpoint")
    else:
        budget = ["--steps", args.train_steps] if args.train_steps else ["--max-seconds", args.train_seconds]
        timings["train_s"] = engine(
            work / "train.log",
            "train",
            "--data",
            work / "data",
            "--out",
            run,
            *budget,
            "--seed",
            args.seed,
            "--device",
            args.device,
            "--overwrite",
        )
        print(f"train: {timings['train_s']:.0f} s; {_last_lines(work / 'train.log', 1)}", flush=True)
    if args.reuse and mesh.is_file():
        reused.append("mesh")
    else:
        timings["extract_s"] = engine(
            work / "extract.log", "extract", "--nerf", ckpt, "--out", mesh, "--device", args.device
        )
        print(f"extract: {timings['extract_s']:.0f} s; {_last_lines(work / 'extract.log', 2)}", flush=True)
    cage_args = {"margin": args.margin, "edge_length": args.edge_length}
    if args.refine_edge:
        cage_args["refine_edge"] = args.refine_edge
    cage_args_path = run / "cage_args.json"
    if (
        args.reuse
        and cage_path.is_file()
        and cage_args_path.is_file()
        and json.loads(cage_args_path.read_text()) == cage_args
    ):
        reused.append("cage")
    else:
        extra = ["--edge-length", args.edge_length] if args.edge_length else []
        if args.refine_edge:
            extra += ["--refine-edge", args.refine_edge, "--refine-box", *np.ravel(REFINE_BOX)]
        timings["cage_s"] = engine(
            work / "cage.log",
            "cage",
            "--nerf",
            ckpt,
            "--mesh",
            mesh,
            "--out",
            cage_path,
            "--margin",
            args.margin,
            *extra,
        )
        cage_args_path.write_text(json.dumps(cage_args) + "\n")
        print(f"cage: {timings['cage_s']:.0f} s; {_last_lines(work / 'cage.log', 1)}", flush=True)
    if reused:
        print(f"reused from {work}: {', '.join(reused)}", flush=True)

    from blender_nerf_deform.engine.geometry.barycentric import inversion_report  # noqa: PLC0415
    from blender_nerf_deform.engine.geometry.mesh_io import load_cage  # noqa: PLC0415

    cage = load_cage(cage_path)
    rest_v, tets = cage["vertices"], cage["tets"]
    edges = np.linalg.norm(rest_v[tets[:, [0, 0, 0, 1, 1, 2]]] - rest_v[tets[:, [1, 2, 3, 2, 3, 3]]], axis=-1)
    n_pieces = cage_components(tets, len(rest_v))
    a, b = GAP_FALLOFF
    in_falloff = int(((rest_v[:, 2] > a) & (rest_v[:, 2] < b)).sum())
    print(
        f"cage: {len(tets)} tets, {len(rest_v)} vertices, {n_pieces} connected piece(s), tet edges median "
        f"{np.median(edges):.3f} / max {edges.max():.3f}, {in_falloff} vertices inside the head's falloff band",
        flush=True,
    )
    surface = np.load(work / "gt_surface_vertices.npy")

    # Renders.
    renders = work / "renders"
    if renders.exists():
        shutil.rmtree(renders)
    renders.mkdir()
    rows = []
    t = engine(
        work / "render_rest.log",
        "render",
        "--nerf",
        ckpt,
        "--cameras",
        test_json,
        "--out",
        renders / "rest",
        "--device",
        args.device,
    )
    rest_score = score(renders / "rest", test_json)
    rest_gt = str(test_json.parent.relative_to(work))
    rows.append({"pose": "rest (no cage)", "gt": rest_gt, **rest_score, "render_s": t})
    np.save(work / "V_identity.npy", rest_v)
    t = engine(
        work / "render_identity.log",
        "render",
        "--nerf",
        ckpt,
        "--cameras",
        test_json,
        "--out",
        renders / "identity",
        "--cage",
        cage_path,
        "--deformed",
        work / "V_identity.npy",
        "--device",
        args.device,
    )
    rows.append(
        {"pose": "identity (cage, V = rest)", "gt": rest_gt, **score(renders / "identity", test_json), "render_s": t}
    )
    for name, fn in maps.items():
        V = fn(rest_v)
        np.save(work / f"V_{name}.npy", V)
        gt_json = work / f"gt_{name}" / "test" / "transforms.json"
        t = engine(
            work / f"render_{name}.log",
            "render",
            "--nerf",
            ckpt,
            "--cameras",
            gt_json,
            "--out",
            renders / name,
            "--cage",
            cage_path,
            "--deformed",
            work / f"V_{name}.npy",
            "--device",
            args.device,
        )
        row = {
            "pose": name,
            "gt": f"gt_{name}/test",
            **score(renders / name, gt_json),
            "render_s": t,
            "undeformed_vs_gt": score(renders / "rest", gt_json)["psnr"],
            "inverted_tets": inversion_report(rest_v, V, tets).n_inverted,
            "cage_error": cage_map_error(surface, rest_v, tets, fn, px_per_unit),
        }
        rows.append(row)

    # Table.
    ref = rest_score["psnr"]
    failed = []
    print()
    print(
        f"| pose | PSNR (RGB on white) | vs rest | alpha PSNR | target (>= {ref - TARGET_DB:.2f} dB) "
        f"| undeformed NeRF vs this GT | cage-map surface error mean / max (px) | inverted tets | render s |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        deformed = "undeformed_vs_gt" in r
        delta = r["psnr"] - ref
        ok = r["psnr"] >= ref - TARGET_DB
        if deformed and not ok:
            failed.append(r["pose"])
        ce = r.get("cage_error")
        verdict = ("met" if ok else "MISSED") if deformed else "-"
        baseline = f"{r['undeformed_vs_gt']:.2f} dB" if deformed else "-"
        geometry = f"{ce['mean_px']:.3f} / {ce['max_px']:.3f}" if ce else "-"
        print(
            f"| {r['pose']} | {r['psnr']:.2f} dB | {delta:+.2f} dB | {r['psnr_alpha']:.2f} dB | {verdict} | "
            f"{baseline} | {geometry} | {r.get('inverted_tets', '-')} | {r['render_s']:.1f} |"
        )
    total = time.perf_counter() - started
    print(
        f"\n{args.test_views} test views, {args.resolution}x{args.resolution} (trained on "
        f"{args.train_resolution} px views); PSNR averaged over views; "
        f"{px_per_unit:.1f} px per world unit at the cameras' distance; total {total:.0f} s"
        + (f" (reused: {', '.join(reused)})" if reused else "")
    )
    results = {
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "rows": rows,
        "timings": timings,
        "reused": reused,
        "cage": {
            "tets": len(tets),
            "vertices": len(rest_v),
            "pieces": n_pieces,
            "edge_median": float(np.median(edges)),
            "edge_max": float(edges.max()),
            "vertices_in_falloff": in_falloff,
        },
        "total_s": total,
        "failed": failed,
    }
    (work / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    if failed:
        print(f"target missed (more than {TARGET_DB} dB below the rest pose): {', '.join(failed)}")
        return 1
    print(f"every deformation within {TARGET_DB} dB of the rest pose")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
