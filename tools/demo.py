#!/usr/bin/env python3
"""`make demo`: the main job on the embedded default scene.

Placeholder until the main-job issue (7) lands: it says what the demo will do
and exits successfully, so `make demo` already proves the setup works.
"""

STEPS = (
    "build the embedded procedural scene and render its dataset with tools/make_dataset.py",
    "train the NeRF within a time budget (python -m blender_nerf_deform.engine train)",
    "extract the filtered mesh and build the tetrahedral cage once (extract, cage)",
    "write demo.blend: a NeRF object, pinned base and keyframed handles bending a part over 24 frames",
    "render the animation headless through the NeRF Deform RenderEngine, as `blender -b demo.blend -a`",
    "write the frames, a GIF and a side-by-side of the original and a deformed frame",
)


def main() -> int:
    print("make demo: the main job is not implemented yet (issue 7). When it lands it will:")
    for number, step in enumerate(STEPS, 1):
        print(f"  {number}. {step}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
