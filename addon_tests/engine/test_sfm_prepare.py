"""`prepare`: photos with no poses → cameras by structure from motion (pycolmap), oriented and written."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from fixtures import REPO
from fixtures.sfm_scene import write_corner_photos
from PIL import Image


def _colmap_info_lines(stderr: str) -> list[str]:
    """COLMAP's (glog's) INFO lines: `I20261207 07:12:35.386056 ...` (older glogs leave out the year)."""
    return [line for line in stderr.splitlines() if re.match(r"I(\d{4})?\d{4} \d\d:\d\d:\d\d", line)]


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", *map(str, args)], cwd=REPO, capture_output=True, text=True
    )


def _similarity_errors(got: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """Camera positions aligned by the best similarity (Umeyama): (largest position error relative to
    the cameras' spread, largest rotation error in degrees)."""
    A, B = got[:, :3, 3], true[:, :3, 3]
    ma, mb = A.mean(0), B.mean(0)
    U, S, Vt = np.linalg.svd((A - ma).T @ (B - mb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    s = (S * np.diag(D)).sum() / ((A - ma) ** 2).sum()
    position = np.linalg.norm(s * (A - ma) @ R.T + mb - B, axis=1).max() / np.linalg.norm(B - mb, axis=1).mean()
    cos = [(np.trace((R @ g[:3, :3]).T @ t[:3, :3]) - 1) / 2 for g, t in zip(got, true)]
    return float(position), float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())


@pytest.mark.slow
def test_prepare_recovers_the_cameras_of_photos_up_to_a_similarity(tmp_path):
    true = write_corner_photos(tmp_path / "photos")
    proc = _cli("prepare", "--images", tmp_path / "photos", "--out", tmp_path / "data")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "14 of 14 photos registered" in proc.stdout
    assert not _colmap_info_lines(proc.stderr), proc.stderr[-2000:]  # COLMAP's chatter stays out of the way
    meta = json.loads((tmp_path / "data" / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["w"] == 320 and meta["h"] == 240
    assert meta["fl_x"] == pytest.approx(260.0, rel=0.01) and meta["cx"] == pytest.approx(160.0, abs=2.0)
    frames = sorted(meta["frames"], key=lambda f: f["file_path"])
    assert [f["file_path"] for f in frames] == [f"images/photo_{k:02d}.png" for k in range(14)]
    assert all((tmp_path / "data" / f["file_path"]).is_file() for f in frames)
    got = np.stack([np.array(f["transform_matrix"]) for f in frames])
    position, rotation = _similarity_errors(got, true)
    assert position < 0.01 and rotation < 0.5, (position, rotation)
    # Oriented as colmap2nerf does: the cameras' mean up is +Z, they stand 4 units from the origin on average.
    up = got[:, :3, 1].mean(0)
    assert up[2] / np.linalg.norm(up) > 0.999
    assert np.linalg.norm(got[:, :3, 3], axis=1).mean() == pytest.approx(4.0, rel=1e-6)
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())  # the work folder is gone


def test_prepare_with_too_few_or_unmatchable_photos_says_so_and_writes_nothing(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(2):
        Image.fromarray(np.zeros((40, 40, 3), np.uint8)).save(photos / f"p{k}.png")
    proc = _cli("prepare", "--images", photos, "--out", tmp_path / "data")
    assert proc.returncode == 2 and "2 photos (.jpg/.png) found; structure from motion needs at least 3" in proc.stderr
    rng = np.random.default_rng(0)
    for k in range(4):  # independent noise: nothing to match between the photos
        Image.fromarray(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)).save(photos / f"n{k}.png")
    proc = _cli("prepare", "--images", photos, "--out", tmp_path / "data")
    # Two photos of another size than the rest: named, before any matching.
    assert (
        proc.returncode == 2 and "p0.png is 40x40, p1.png is 40x40, where 4 of the 6 photos are 160x120" in proc.stderr
    )
    for k in range(2):
        (photos / f"p{k}.png").unlink()
    proc = _cli("prepare", "--images", photos, "--out", tmp_path / "data")
    assert proc.returncode == 2 and "structure from motion registered" in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert not _colmap_info_lines(proc.stderr), proc.stderr[-2000:]  # COLMAP's warnings only, then the error
    assert "the photos are small (160x120): if you have them at full size, use those" in proc.stderr
    proc = _cli(
        "prepare", "--images", photos, "--out", tmp_path / "data", "--colmap-log"
    )  # all of COLMAP's log, asked for
    assert proc.returncode == 2 and "structure from motion registered" in proc.stderr
    assert len(_colmap_info_lines(proc.stderr)) > 10, proc.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]  # no dataset, no work folder left


def test_prepare_refuses_a_destination_that_holds_files(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "mine.txt").write_text("keep")
    write_corner_photos(tmp_path / "photos", n_views=3, width=64, height=48, focal=60.0)
    proc = _cli("prepare", "--images", tmp_path / "photos", "--out", tmp_path / "data")
    assert proc.returncode == 2 and "exists and is not an empty folder" in proc.stderr
    assert (tmp_path / "data" / "mine.txt").read_text() == "keep"


@pytest.mark.parametrize("case", ["no such folder", "max-size too small", "unwritable destination", "corrupt photo"])
def test_prepare_bad_input_is_one_error_line(tmp_path, case):
    photos = tmp_path / "photos"
    out = tmp_path / "data"
    extra = []
    if case != "no such folder":
        write_corner_photos(photos, n_views=4, width=64, height=48, focal=60.0)
    if case == "max-size too small":
        extra = ["--max-size", "10"]
    if case == "unwritable destination":
        out = "/sys/nerf_deform_prepare_out"  # root ignores permission bits; /sys refuses everyone
    if case == "corrupt photo":
        (photos / "photo_01.png").write_bytes(b"not a png at all")
    proc = _cli("prepare", "--images", photos, "--out", out, *extra)
    lines = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ([] if case == "no such folder" else ["photos"])
