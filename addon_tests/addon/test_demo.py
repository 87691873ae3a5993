"""The main job end to end, reduced: `tools/demo.py --quick` from scene to frames, GIF and side-by-side.

It runs the real pipeline (Cycles dataset, training, the installed extension's operators in one
Blender process, Render Animation in a fresh one), only smaller. The assertions are about the
picture: the arm bent over, the pinned base stayed.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from fixtures import REPO
from PIL import Image

sys.path.insert(0, str(REPO))
from tools.default_scene import REGIONS  # noqa: E402
from tools.make_dataset import project  # noqa: E402


def _box_corners(bounds):
    (x0, y0, z0), (x1, y1, z1) = bounds
    return np.array([(x, y, z) for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], dtype=np.float64)


def _box_mask(bounds, cameras, shape):
    """Pixels inside the image-space bounding rectangle of a world box."""
    frame = cameras["frames"][0]
    uv = project(
        _box_corners(bounds), frame["transform_matrix"], cameras["fl_x"], cameras["fl_y"], cameras["cx"], cameras["cy"]
    )
    (u0, v0), (u1, v1) = np.floor(uv.min(0)).astype(int), np.ceil(uv.max(0)).astype(int)
    mask = np.zeros(shape, dtype=bool)
    mask[max(v0, 0) : max(v1, 0), max(u0, 0) : max(u1, 0)] = True
    return mask


@pytest.fixture(scope="module")
def quick_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    proc = subprocess.run(
        [sys.executable, str(REPO / "tools" / "demo.py"), "--quick", "--out", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out, proc.stdout


@pytest.mark.slow
def test_quick_demo_writes_everything_it_announces(quick_demo):
    out, stdout = quick_demo
    frames = sorted((out / "frames").glob("frame_*.png"))
    assert [p.name for p in frames] == [f"frame_{k:04d}.png" for k in range(1, 7)]
    for name in ("demo.blend", "demo.gif", "side_by_side.png", "cameras.json", "run/nerf.ckpt"):
        assert (out / name).is_file(), name
        assert str(out / name) in stdout or name in ("cameras.json", "run/nerf.ckpt"), f"{name} not announced"
    gif = Image.open(out / "demo.gif")
    assert gif.n_frames == 2 * len(frames) - 2  # forth and back
    side = Image.open(out / "side_by_side.png")
    assert side.width == 2 * Image.open(frames[0]).width


@pytest.mark.slow
def test_quick_demo_bends_the_arm_and_keeps_the_base(quick_demo):
    out, _ = quick_demo
    cameras = json.loads((out / "cameras.json").read_text())
    first, last = (
        np.asarray(Image.open(out / "frames" / f"frame_{k:04d}.png").convert("RGBA"))[..., 3] / 255.0 for k in (1, 6)
    )
    opaque_first, opaque_last = first > 0.5, last > 0.5

    # The arm's tip (top band and flag) leaves where it stood: most of its pixels go empty.
    tip = _box_mask(REGIONS["arm_tip"]["bounds"], cameras, first.shape) & opaque_first
    assert tip.sum() > 20, "the tip is not visible in the first frame"
    assert (opaque_last & tip).sum() < 0.5 * tip.sum()
    # ... and appears somewhere it was not.
    appeared = opaque_last & ~opaque_first
    assert appeared.sum() > 0.3 * tip.sum()

    # The pinned base stays: outside the arm's rest rectangle its silhouette is unchanged.
    base = _box_mask(REGIONS["base"]["bounds"], cameras, first.shape) & ~_box_mask(
        REGIONS["arm"]["bounds"], cameras, first.shape
    )
    a, b = opaque_first & base, opaque_last & base
    assert a.sum() > 50
    assert (a & b).sum() / (a | b).sum() > 0.9


_RIG = """
import sys
sys.path.insert(0, {repo!r})
from tools import demo
bpy = demo._start_blender()
bpy.ops.wm.open_mainfile(filepath={blend!r})
scene = bpy.context.scene
handles = {{o.name: o for o in scene.objects if o.nerf_deform.role == "HANDLE"}}
for handle in handles.values():
    handle.animation_data_clear()  # frame 1 is the rest pose: the handles stay there
demo.rig_handles_with_bones(bpy, handles["Middle Handle"], handles["Tip Handle"], scene.frame_end)
bpy.ops.wm.save_as_mainfile(filepath={rig!r})
"""

_RENDER = """
import sys
sys.path.insert(0, {repo!r})
from tools import demo
bpy = demo._start_blender()
bpy.ops.wm.open_mainfile(filepath={rig!r})
scene = bpy.context.scene
scene.frame_start, scene.frame_end = {start}, {end}
scene.render.filepath = "//{folder}/frame_"
assert bpy.ops.render.render(animation=True) == {{"FINISHED"}}
"""


@pytest.mark.slow
def test_an_armature_rig_bends_the_arm_and_a_split_render_matches_one_run(quick_demo):
    """The handles parented to a two-bone chain (tools/demo.py --rig armature), the bones keyed: the
    bones move the NeRF's rendered arm, nothing folds, and frames rendered as a farm splits them
    (1-3 and 4-6 in separate processes, as `blender -b -s/-e -a`) are the frames of one run."""
    out, _ = quick_demo
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(out / "blender_user")}

    def run(script):
        proc = subprocess.run(
            [sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True, timeout=600
        )
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        return proc.stdout + proc.stderr

    rig = out / "rig.blend"  # beside demo.blend: the checkpoint's relative path holds
    run(_RIG.format(repo=str(REPO), blend=str(out / "demo.blend"), rig=str(rig)))
    logs = [
        run(_RENDER.format(repo=str(REPO), rig=str(rig), start=s, end=e, folder=f))
        for s, e, f in ((1, 6, "rig_one"), (1, 3, "rig_split"), (4, 6, "rig_split"))
    ]
    assert not any("inverted" in log for log in logs), "a rendered frame reported folded cage tets"

    names = [f"frame_{k:04d}.png" for k in range(1, 7)]
    assert sorted(p.name for p in (out / "rig_one").iterdir()) == names
    for name in names:
        one = np.asarray(Image.open(out / "rig_one" / name))
        assert np.array_equal(one, np.asarray(Image.open(out / "rig_split" / name))), name

    cameras = json.loads((out / "cameras.json").read_text())
    first, last = (
        np.asarray(Image.open(out / "rig_one" / names[k]).convert("RGBA"))[..., 3] / 255.0 > 0.5 for k in (0, 5)
    )
    tip = _box_mask(REGIONS["arm_tip"]["bounds"], cameras, first.shape) & first
    assert tip.sum() > 20 and (last & tip).sum() < 0.5 * tip.sum()  # the bones carried the tip away
    base = _box_mask(REGIONS["base"]["bounds"], cameras, first.shape) & ~_box_mask(
        REGIONS["arm"]["bounds"], cameras, first.shape
    )
    assert (first & base & last).sum() / ((first | last) & base).sum() > 0.9  # the pinned base stays
