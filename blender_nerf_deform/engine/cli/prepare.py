"""`prepare`: photos with no poses → a transforms.json dataset (structure from motion, engine/sfm/).

python -m blender_nerf_deform.engine prepare --images DIR --out DATASET_DIR
    [--matcher exhaustive|sequential] [--max-size PX] [--seed N] [--colmap-log]
"""

from __future__ import annotations

from ..sfm.prepare import prepare


def main(args) -> int:
    summary = prepare(
        args.images, args.out, matcher=args.matcher, max_size=args.max_size, seed=args.seed, colmap_log=args.colmap_log
    )
    t = summary["timings"]
    print(
        f"prepare: {summary['registered']} of {summary['photos']} photos registered "
        f"({summary['points']} sparse points, "
        f"camera {summary['camera_model']}); features {t['features_s']:.1f}s, matching {t['matching_s']:.1f}s, "
        f"mapping {t['mapping_s']:.1f}s -> {args.out}/transforms.json"
    )
    return 0
