#!/usr/bin/env python3
"""PSNR per frame between two folders of rendered frames (same names), e.g. before and after a change.

    .venv/bin/python tools/compare_frames.py OLD_DIR NEW_DIR [--min-db 60]

Compares every PNG of OLD_DIR with the PNG of the same name in NEW_DIR over all channels
(RGBA, 8-bit values scaled to [0, 1]); prints one line per frame and the lowest. Exits 1 when a
frame is missing or below --min-db.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="compare_frames.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--min-db", type=float, default=60.0)
    args = parser.parse_args(argv)
    names = sorted(p.name for p in args.old.glob("*.png"))
    if not names:
        print(f"error: {args.old} holds no PNG frames", file=sys.stderr)
        return 2
    worst, failed = float("inf"), False
    for name in names:
        other = args.new / name
        if not other.is_file():
            print(f"{name}\tmissing in {args.new}")
            failed = True
            continue
        a = np.asarray(Image.open(args.old / name).convert("RGBA"), np.float64) / 255.0
        b = np.asarray(Image.open(other).convert("RGBA"), np.float64) / 255.0
        if a.shape != b.shape:
            print(f"{name}\tsizes differ: {a.shape} vs {b.shape}")
            failed = True
            continue
        mse = float(np.mean((a - b) ** 2))
        db = float("inf") if mse == 0 else -10.0 * np.log10(mse)
        differing = int(np.any(a != b, axis=-1).sum())
        print(f"{name}\t{db:.2f} dB\t{differing} differing pixels")
        worst = min(worst, db)
        failed |= db < args.min_db
    print(f"lowest PSNR {worst:.2f} dB over {len(names)} frames (threshold {args.min_db:g} dB)")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
