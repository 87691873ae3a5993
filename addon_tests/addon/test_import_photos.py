"""Import Photos: a folder of photos → cameras (structure from motion, the worker's prepare) →
training → the NeRF object, as one operator; too few or unmatchable photos are reported and leave
no dataset behind. Real worker, ray-cast photos of a textured corner (fixtures.sfm_scene)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from fixtures.sfm_scene import write_corner_photos
from PIL import Image


@pytest.mark.slow
def test_import_photos_finds_the_cameras_trains_and_ends_with_a_nerf_object(addon, tmp_path, capfd):
    bpy = addon
    from blender_nerf_deform.addon import api

    write_corner_photos(tmp_path / "photos", n_views=8, width=160, height=120, focal=130.0)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))  # the run folder goes beside it
    nerf = api.import_photos(tmp_path / "photos", steps=40, seconds=0, device="cpu")
    printed = capfd.readouterr().out
    # Progress through both stages, in order, each advancing.
    cameras = re.findall(r"Import Photos: 1/2 cameras: +([0-9.]+)% (.*)", printed)
    training = re.findall(r"Import Photos: 2/2 training: +([0-9.]+)% step (\d+)", printed)
    assert len(cameras) >= 3 and any("matching" in m for _, m in cameras), printed[-3000:]
    assert float(cameras[-1][0]) > float(cameras[0][0])
    assert training and printed.rindex("1/2 cameras") < printed.index("2/2 training"), printed[-3000:]
    # The dataset and the run where Import Photos puts them by default, beside the .blend.
    run = tmp_path / "nerf_runs" / "photos"
    meta = json.loads((run / "dataset" / "transforms.json").read_text())
    assert len(meta["frames"]) == 8 and meta["camera_model"] == "OPENCV"
    assert all((run / "dataset" / f["file_path"]).is_file() for f in meta["frames"])
    assert json.loads((run / "train.json").read_text())["steps"] == 40
    assert nerf.nerf_deform.role == "NERF" and bpy.path.abspath(nerf.nerf_deform.checkpoint) == str(run / "nerf.ckpt")
    assert [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"] == [nerf]
    # Again on the same photos: the run folder is taken, nothing is touched.
    stamp = (run / "nerf.ckpt").stat().st_mtime_ns
    with pytest.raises(RuntimeError, match="already holds a NeRF"):
        bpy.ops.nerf_deform.import_photos(photos=str(tmp_path / "photos"), steps=10, seconds=0)
    assert (run / "nerf.ckpt").stat().st_mtime_ns == stamp


def test_too_few_no_or_unmatchable_photos_are_reported_and_leave_no_dataset(addon, tmp_path):
    bpy = addon
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "notes.txt").write_text("not a photo")
    with pytest.raises(RuntimeError, match=r"holds 0 photos \(.jpg/.png\); finding their cameras needs at least 3"):
        bpy.ops.nerf_deform.import_photos(photos=str(photos), steps=10, seconds=0)
    for k in range(2):
        Image.fromarray(np.full((40, 40, 3), 60 * k, np.uint8)).save(photos / f"p{k}.png")
    with pytest.raises(RuntimeError, match="holds 2 photos"):
        bpy.ops.nerf_deform.import_photos(photos=str(photos), steps=10, seconds=0)
    with pytest.raises(RuntimeError, match="photos folder .*nowhere does not exist"):
        bpy.ops.nerf_deform.import_photos(photos=str(tmp_path / "nowhere"), steps=10, seconds=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos", "shot.blend"]
    # Enough photos, but nothing to match between them: the worker's prepare says so, in one line,
    # and the folders it made for the dataset are gone again.
    rng = np.random.default_rng(0)
    for k in range(4):
        Image.fromarray(rng.integers(0, 255, (90, 120, 3), dtype=np.uint8)).save(photos / f"n{k}.png")
    with pytest.raises(RuntimeError, match=r"p0\.png is 40x40, p1\.png is 40x40, where 4 of the 6 photos are 120x90"):
        bpy.ops.nerf_deform.import_photos(photos=str(photos), steps=10, seconds=0, device="cpu")
    for k in range(2):
        (photos / f"p{k}.png").unlink()
    with pytest.raises(RuntimeError, match=r"Import Photos: 1/2 cameras: structure from motion registered") as caught:
        bpy.ops.nerf_deform.import_photos(photos=str(photos), steps=10, seconds=0, device="cpu")
    assert "Traceback" not in str(caught.value) and len(str(caught.value).strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos", "shot.blend"]
    assert not [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]
