#!/usr/bin/env python3
"""Render a `make demo` scene with this tree and check the frames against another tree's, pixel for pixel.

    python tools/frames_identical.py --demo demo_out --out /tmp/frames_before
    (change the code)
    python tools/frames_identical.py --demo demo_out --out /tmp/frames_after --reference /tmp/frames_before

For refactors that must not change a single pixel. Each run installs this tree's extension in a
Blender user folder private to the run (as `make demo` does), then renders the demo's .blend:

- F12 stills of the first (rest) and last (bent) frame, `bpy.ops.render.render(write_still=True)`;
- the animation, as `blender -b demo.blend -a` does;
- on the command line, `engine render` of the demo camera at rest and through a cage with a bent
  pose. The cage is built once, by the first run (fTetWild is not deterministic), and the runs given
  `--reference` take it from there, so both trees render the same cage.

With `--reference`, every PNG is compared as pixels (not bytes: PNG metadata may carry a date)
and the exit status is 1 when any differs or is missing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from tools.demo import _check, _start_blender, blender_env, install_extension, run  # noqa: E402


def _bent(rest):
    """A smooth, fold-free bend of the cage about its lowest point: deterministic, so both trees get it."""
    import numpy as np

    low, high = rest.min(0), rest.max(0)
    t = (rest[:, 2] - low[2]) / max(high[2] - low[2], 1e-9)
    angle = 0.6 * t**2
    y, z = rest[:, 1] - low[1], rest[:, 2] - low[2]
    out = rest.copy()
    out[:, 1] = low[1] + y * np.cos(angle) - z * np.sin(angle)
    out[:, 2] = low[2] + y * np.sin(angle) + z * np.cos(angle)
    return out.astype(rest.dtype)


def _cli_inputs(demo: Path, folder: Path) -> None:
    """The cage and the bent pose the command-line renders use (built once: see the module docstring)."""
    import numpy as np

    folder.mkdir(parents=True)
    ckpt = demo / "run" / "nerf.ckpt"
    run("-m", "blender_nerf_deform.engine", "extract", "--nerf", ckpt, "--out", folder / "mesh.ply")
    run(
        "-m",
        "blender_nerf_deform.engine",
        "cage",
        "--nerf",
        ckpt,
        "--mesh",
        folder / "mesh.ply",
        "--out",
        folder / "cage.npz",
    )
    with np.load(folder / "cage.npz") as cage:
        np.save(folder / "bent.npy", _bent(cage["vertices"]))


def render_in_blender(config: dict) -> int:
    bpy = _start_blender()
    bpy.ops.wm.open_mainfile(filepath=config["blend"])
    scene = bpy.context.scene
    out = Path(config["out"])
    for frame in (scene.frame_start, scene.frame_end):
        scene.frame_set(frame)
        scene.render.filepath = str(out / "f12" / f"still_{frame:04d}.png")
        _check(bpy.ops.render.render(write_still=True), f"Render Image (frame {frame})")
    scene.render.filepath = str(out / "animation" / "frame_")
    _check(bpy.ops.render.render(animation=True), "Render Animation")
    return 0


def _pixels(path: Path):
    import numpy as np
    from PIL import Image

    with Image.open(path) as image:
        return np.asarray(image)


def compare(out: Path, reference: Path) -> int:
    names = sorted(str(p.relative_to(reference)) for p in reference.rglob("*.png"))
    if not names:
        print(f"frames_identical: no PNG under {reference}")
        return 1
    differ = []
    for name in names:
        mine = out / name
        if not mine.is_file():
            differ.append(f"{name}: missing")
            continue
        a, b = _pixels(reference / name), _pixels(mine)
        if a.shape != b.shape:
            differ.append(f"{name}: shape {b.shape}, reference {a.shape}")
        elif (a != b).any():
            d = abs(a.astype(int) - b.astype(int))
            differ.append(f"{name}: {(d.max(-1) > 0).sum()} pixels differ, by up to {d.max()}")
    for line in differ:
        print("DIFFERS", line)
    print(f"frames_identical: {len(names) - len(differ)} of {len(names)} images identical to {reference}")
    return 1 if differ else 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--demo", type=Path, required=True, help="the --out folder of a `make demo` (tools/demo.py) run")
    p.add_argument("--out", type=Path, required=True, help="new folder for this tree's renders")
    p.add_argument("--reference", type=Path, help="an earlier --out to compare with (and take the cage from)")
    p.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return render_in_blender(json.loads(args.child.read_text()))

    demo, out = args.demo.resolve(), args.out.resolve()
    if not (demo / "demo.blend").is_file():
        raise SystemExit(f"frames_identical: {demo} holds no demo.blend (run tools/demo.py --out {demo})")
    if out.exists():
        raise SystemExit(f"frames_identical: --out {out} exists; give a new folder")
    out.mkdir(parents=True)
    os.environ.setdefault("NUMBA_CACHE_DIR", str(REPO / "build" / "numba_cache"))

    user = out / "blender_user"
    install_extension(out, user)
    config = out / "config.json"
    config.write_text(json.dumps({"blend": str(demo / "demo.blend"), "out": str(out)}))
    run("tools/frames_identical.py", "--demo", demo, "--out", out, "--child", config, env=blender_env(user))

    inputs = (args.reference.resolve() if args.reference else out) / "cli_inputs"
    if not args.reference:
        _cli_inputs(demo, inputs)
    engine = ("-m", "blender_nerf_deform.engine", "render", "--nerf", demo / "run" / "nerf.ckpt")
    cameras = ("--cameras", demo / "cameras.json")
    run(*engine, *cameras, "--out", out / "cli_rest")
    run(*engine, *cameras, "--out", out / "cli_bent", "--cage", inputs / "cage.npz", "--deformed", inputs / "bent.npy")
    return compare(out, args.reference.resolve()) if args.reference else 0


if __name__ == "__main__":
    raise SystemExit(main())
