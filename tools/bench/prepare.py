#!/usr/bin/env python3
"""Benchmark: `prepare` (structure from motion with pycolmap) on the photos of a dataset whose cameras are known.

Runs the prepare stage on the dataset's photos alone (no poses given), then compares
the cameras it recovered with the dataset's own after the best similarity
(Umeyama on the camera centres): mean and max rotation error in degrees, mean and
max position error relative to the camera spread (RMS distance of the true
centres from their centroid). Reports wall time per stage and registered photos.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/prepare.py \\
        --data ../shared/datasets/fox --max-size 1024 --json /tmp/prepare_fox.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_nerf_deform.engine.nerf.dataset import load_dataset  # noqa: E402
from blender_nerf_deform.engine.sfm.prepare import prepare  # noqa: E402


def similarity(src: np.ndarray, dst: np.ndarray):
    """Umeyama: s, R, t minimising |s R src + t - dst|^2 over corresponding points (N, 3)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(sig) @ d) / (a**2).sum(1).mean())
    return scale, rot, mu_d - scale * rot @ mu_s


def compare(got: dict, true: dict) -> dict:
    names = sorted(set(got) & set(true))
    g = np.stack([got[n] for n in names])
    t = np.stack([true[n] for n in names])
    s, rot, off = similarity(g[:, :3, 3], t[:, :3, 3])
    pos = (s * g[:, :3, 3] @ rot.T + off) - t[:, :3, 3]
    spread = float(np.sqrt(((t[:, :3, 3] - t[:, :3, 3].mean(0)) ** 2).sum(1).mean()))
    rel = np.linalg.norm(pos, axis=1) / spread
    angles = []
    for gi, ti in zip(g, t):
        r = ti[:3, :3].T @ rot @ gi[:3, :3]
        angles.append(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))
    return {
        "compared": len(names),
        "rotation_deg_mean": float(np.mean(angles)),
        "rotation_deg_max": float(np.max(angles)),
        "position_rel_mean": float(rel.mean()),
        "position_rel_max": float(rel.max()),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/datasets/fox")
    ap.add_argument("--max-size", type=int, default=1600)
    ap.add_argument("--matcher", default="exhaustive")
    ap.add_argument("--json")
    ap.add_argument("--keep", help="copy the dataset prepare wrote to this folder (to train on its poses)")
    args = ap.parse_args()
    ds = load_dataset(args.data, load_images=False)
    true = {Path(c.name).stem: np.asarray(c.c2w) for c in ds.cameras}
    files = {}
    for fr in json.loads(Path(ds.source).read_text())["frames"]:
        p = Path(ds.source).parent / fr["file_path"]
        if p.is_file():
            files[p.stem] = p
    with tempfile.TemporaryDirectory(prefix="bench_prepare.") as tmp:
        photos = Path(tmp) / "photos"
        photos.mkdir()
        for _stem, p in files.items():
            shutil.copy(p, photos / p.name)
        t0 = time.perf_counter()
        summary = prepare(photos, Path(tmp) / "out", matcher=args.matcher, max_size=args.max_size)
        wall = time.perf_counter() - t0
        out = json.loads((Path(tmp) / "out" / "transforms.json").read_text())
        got = {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"]) for f in out["frames"]}
        if args.keep:
            shutil.copytree(Path(tmp) / "out", args.keep)
    result = {
        "photos": len(files),
        "registered": summary["registered"],
        "wall_s": wall,
        "timings": summary["timings"],
        "camera_model": summary["camera_model"],
        "max_size": args.max_size,
        "matcher": args.matcher,
        **compare(got, true),
    }
    print(json.dumps(result, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
