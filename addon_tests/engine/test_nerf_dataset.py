"""transforms.json loading: both forms, downscaling, scene bounds, and a clear error for each bad input."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from fixtures import REPO, SHARED_DATASETS
from fixtures.sphere_data import look_at, write_sphere_dataset
from PIL import Image

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.nerf.dataset import load_dataset


def _write(folder, meta, images=None, size=(8, 6), mode="RGBA"):
    folder.mkdir(parents=True, exist_ok=True)
    for name in images or []:
        color = (200, 100, 50, 128) if mode == "RGBA" else (200, 100, 50)
        Image.new(mode, size, color).save(folder / name)
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def _frame(name, c2w=None):
    return {"file_path": name, "transform_matrix": (np.eye(4) if c2w is None else c2w).tolist()}


def test_nerf_synthetic_form(tmp_path):
    folder = write_sphere_dataset(tmp_path / "s", n_views=3, size=16)
    ds = load_dataset(folder)
    assert len(ds) == 3 and ds.images.shape == (3, 16, 16, 4) and ds.images.dtype == np.float32
    cam = ds.cameras[0]
    assert cam.fx == pytest.approx(0.5 * 16 / math.tan(0.45)) and cam.fx == cam.fy and (cam.cx, cam.cy) == (8, 8)
    np.testing.assert_array_equal(ds.aabb, [[-1.5] * 3, [1.5] * 3])
    assert ds.names == ["r_0", "r_1", "r_2"]
    assert ds.images[..., 3].max() == 1.0 and ds.images[..., 3].min() == 0.0


def test_instant_ngp_form_with_per_frame_intrinsics_rgb_and_jpg(tmp_path):
    meta = {
        "fl_x": 10.0,
        "fl_y": 12.0,
        "cx": 4.5,
        "cy": 2.5,
        "w": 8,
        "h": 6,
        "aabb_scale": 2,
        "frames": [_frame("a.jpg"), {**_frame("b.png"), "fl_x": 20.0}],
    }
    folder = _write(tmp_path, meta, ["b.png"], mode="RGB")
    Image.new("RGB", (8, 6), (10, 20, 30)).save(tmp_path / "a.jpg")
    ds = load_dataset(folder)
    a, b = ds.cameras
    assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (10, 12, 4.5, 2.5, 8, 6)
    assert b.fx == 20 and b.fy == 12
    np.testing.assert_array_equal(ds.images[..., 3], 1.0)  # RGB: opaque
    # instant-ngp's scene: aabb_scale (2) unit cubes about its centre, mapped back by its default
    # scale 0.33 and offset 0.5; the unit cube itself is the inner box.
    np.testing.assert_allclose(ds.aabb, [[-1 / 0.33] * 3, [1 / 0.33] * 3], rtol=1e-6)
    np.testing.assert_allclose(ds.inner_aabb, [[-0.5 / 0.33] * 3, [0.5 / 0.33] * 3], rtol=1e-6)
    assert ds.source_format == "instant-ngp" and not ds.has_alpha


def test_explicit_aabb_and_bounds_derived_from_cameras(tmp_path):
    eyes = [(4, 0, 0), (0, 4, 0), (-4, 0, 0), (0, -4, 1)]
    frames = [_frame(f"{k}.png", look_at(np.array(e, float) + [1, 2, 3], target=(1, 2, 3))) for k, e in enumerate(eyes)]
    meta = {"fl_x": 8.0, "w": 8, "h": 6, "frames": frames}
    _write(tmp_path / "derived", meta, [f"{k}.png" for k in range(4)])
    ds = load_dataset(tmp_path / "derived")
    np.testing.assert_allclose(ds.aabb.mean(0), [1, 2, 3], atol=1e-4)  # centred where the axes meet
    half = 0.5 * (ds.aabb[1] - ds.aabb[0])
    dist = np.mean([np.linalg.norm(e) for e in eyes])
    np.testing.assert_allclose(half, dist, rtol=1e-4)  # the cameras stand on the box (not what they frame: 3/8 of it)
    _write(tmp_path / "box", {**meta, "aabb": [[-1, -2, -3], [1, 2, 3]]}, [f"{k}.png" for k in range(4)])
    np.testing.assert_array_equal(load_dataset(tmp_path / "box").aabb, [[-1, -2, -3], [1, 2, 3]])


def test_downscale_box_filters_premultiplied_and_scales_intrinsics(tmp_path):
    img = np.zeros((4, 6, 4), np.uint8)
    img[:, :3] = (255, 0, 0, 255)  # opaque red on the left, transparent black on the right
    img[:, 3:] = (0, 0, 0, 0)
    img[:1, 3] = (0, 0, 255, 255)
    tmp_path.mkdir(exist_ok=True)
    Image.fromarray(img, "RGBA").save(tmp_path / "i.png")
    (tmp_path / "transforms.json").write_text(
        json.dumps({"fl_x": 6.0, "cx": 3.0, "cy": 2.0, "frames": [_frame("i.png")]})
    )
    ds = load_dataset(tmp_path, downscale=2)
    assert ds.images.shape == (1, 2, 3, 4)
    cam = ds.cameras[0]
    assert (cam.fx, cam.cx, cam.cy, cam.width, cam.height) == (3.0, 1.5, 1.0, 3, 2)
    px = ds.images[0, 0, 1]  # mixes 2 opaque red, 1 opaque blue, 1 transparent pixel
    np.testing.assert_allclose(px, [2 / 3, 0, 1 / 3, 0.75], atol=1e-6)  # colour not darkened by the transparent one
    np.testing.assert_allclose(ds.images[0, 0, 0], [1, 0, 0, 1])


def _expect(tmp_path, meta, match, images=(), **kw):
    _write(tmp_path, meta, list(images), **kw)
    with pytest.raises(EngineError, match=match) as exc:
        load_dataset(tmp_path)
    assert "\n" not in str(exc.value)
    return str(exc.value)


def test_bad_datasets_each_get_a_clear_error(tmp_path):
    ok = {"camera_angle_x": 0.7, "frames": [_frame("a.png")]}
    _expect(
        tmp_path / "1",
        {**ok, "frames": [_frame("missing.png")]},
        r"none of its 1 frames has an image file.*missing\.png",
    )
    _expect(tmp_path / "2", {"camera_angle_x": 0.7}, r"missing key `frames`")
    _expect(tmp_path / "3", {**ok, "frames": []}, r"`frames` is empty")
    _expect(
        tmp_path / "4", {"frames": [_frame("a.png")]}, r"frames\[0\]: missing key `camera_angle_x` or `fl_x`", ["a.png"]
    )
    _expect(
        tmp_path / "5",
        {**ok, "frames": [{"file_path": "a.png"}]},
        r"frames\[0\]: missing key `transform_matrix`",
        ["a.png"],
    )
    bad = np.eye(4)
    bad[0, 3] = np.nan
    _expect(
        tmp_path / "6",
        {**ok, "frames": [{"file_path": "a.png", "transform_matrix": [[1, 0, 0, "NaN"]] * 4}]},
        r"non-finite|not a 4x4",
        ["a.png"],
    )
    _expect(
        tmp_path / "6b",
        {**ok, "frames": [{"file_path": "a.png", "transform_matrix": np.where(np.isnan(bad), 1e400, bad).tolist()}]},
        r"frames\[0\]: `transform_matrix` has non-finite values",
        ["a.png"],
    )
    _expect(tmp_path / "7", {**ok, "frames": [{"transform_matrix": np.eye(4).tolist()}]}, r"missing key `file_path`")
    (tmp_path / "8").mkdir()
    Image.new("RGBA", (8, 6)).save(tmp_path / "8" / "a.png")
    Image.new("RGBA", (8, 7)).save(tmp_path / "8" / "b.png")
    _expect(tmp_path / "8", {**ok, "frames": [_frame("a.png"), _frame("b.png")]}, r"b\.png: image is 8x7.*same size")
    (tmp_path / "9").mkdir()
    (tmp_path / "9" / "a.png").write_bytes(b"not a png")
    _expect(tmp_path / "9", ok, r"a\.png: cannot read image")
    _expect(tmp_path / "10", {**ok, "camera_model": "FOV"}, r"camera_model 'FOV' is not supported", ["a.png"])
    _expect(tmp_path / "10b", {**ok, "k4": 0.1}, r"`k4` = 0.1 belongs to the fisheye model", ["a.png"])
    _expect(
        tmp_path / "10c",
        {**ok, "camera_model": "PINHOLE", "k1": 0.2},
        r"camera_model PINHOLE has no distortion",
        ["a.png"],
    )
    (tmp_path / "11").mkdir()
    (tmp_path / "11" / "transforms.json").write_text("{ not json")
    with pytest.raises(EngineError, match=r"transforms\.json: not valid JSON"):
        load_dataset(tmp_path / "11")
    with pytest.raises(EngineError, match=r"no transforms\.json"):
        load_dataset(tmp_path)  # a folder without one
    with pytest.raises(EngineError, match="no such file"):
        load_dataset(tmp_path / "nowhere")


def test_cli_reports_bad_input_in_one_line_and_exit_2(tmp_path):
    env_cmd = [sys.executable, "-m", "blender_nerf_deform.engine"]
    _write(tmp_path / "d", {"camera_angle_x": 0.7, "frames": [_frame("gone.png")]})
    for args, needle in [
        (
            ["train", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "run"), "--steps", "1"],
            "frames has an image file (first: ",
        ),
        (
            ["eval", "--nerf", str(tmp_path / "none.ckpt"), "--data", str(tmp_path / "d")],
            "none.ckpt: checkpoint not found",
        ),
    ]:
        proc = subprocess.run(env_cmd + args, cwd=REPO, capture_output=True, text=True)
        assert proc.returncode == 2, proc.stderr
        last = proc.stderr.strip().splitlines()[-1]
        assert last.startswith("error: ") and needle in last, proc.stderr


def test_lego_200_loads_with_its_documented_cameras_and_bounds():
    lego = SHARED_DATASETS / "lego_200"
    if not (lego / "transforms.json").is_file():
        pytest.skip("../shared/datasets/lego_200 is not on this machine")
    ds = load_dataset(lego, downscale=4)
    assert len(ds) == 90 and ds.images.shape == (90, 50, 50, 4)
    meta = json.loads((lego / "transforms.json").read_text())
    cam = ds.cameras[0]
    assert cam.fx == pytest.approx(0.5 * 200 / math.tan(0.5 * meta["camera_angle_x"]) / 4)
    assert (cam.cx, cam.cy, cam.width, cam.height) == (25.0, 25.0, 50, 50)
    np.testing.assert_array_equal(ds.aabb, [[-1.5] * 3, [1.5] * 3])
    np.testing.assert_allclose(np.linalg.norm(cam.c2w[:3, 3]), 4.03, atol=0.05)  # cameras ~4 units out


def test_frames_without_an_image_file_are_skipped_with_a_warning(tmp_path, caplog):
    """instant-ngp's own fox lists 67 frames for the 50 photos its repository ships: skip, as it does."""
    (tmp_path / "images").mkdir()
    Image.new("RGBA", (8, 6)).save(tmp_path / "images" / "a.png")
    frames = [{"file_path": f"images/{n}.png", "transform_matrix": np.eye(4).tolist()} for n in ("a", "gone1", "gone2")]
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    ds = load_dataset(tmp_path)
    assert ds.names == ["a"] and ds.images.shape[0] == 1
    assert "2 of 3 frames have no image file and are skipped" in caplog.text


def test_instant_ngp_distortion_keys_become_the_cameras_lens(tmp_path):
    from blender_nerf_deform.engine.nerf.camera import Distortion

    (tmp_path / "a.png").parent.mkdir(exist_ok=True)
    Image.new("RGB", (8, 6)).save(tmp_path / "a.png")
    base = {
        "fl_x": 7.0,
        "fl_y": 7.0,
        "cx": 4.0,
        "cy": 3.0,
        "w": 8,
        "h": 6,
        "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}],
    }
    for extra, lens in (
        (
            {"k1": 0.1, "k2": -0.02, "p1": 0.001, "p2": 0.002},
            Distortion("opencv", k1=0.1, k2=-0.02, p1=0.001, p2=0.002),
        ),
        ({"is_fisheye": True, "k1": 0.05, "k4": 0.001}, Distortion("fisheye", k1=0.05, k4=0.001)),
        ({"camera_model": "OPENCV_FISHEYE", "k1": 0.05}, Distortion("fisheye", k1=0.05)),
        ({"camera_model": "OPENCV"}, None),
        ({}, None),
    ):
        (tmp_path / "transforms.json").write_text(json.dumps({**base, **extra}))
        assert load_dataset(tmp_path).cameras[0].distortion == lens, extra
    # Per-frame keys override the top level (instant-ngp and nerfstudio both allow it).
    frame = {**base["frames"][0], "k1": 0.3}
    (tmp_path / "transforms.json").write_text(json.dumps({**base, "k1": 0.1, "frames": [frame]}))
    assert load_dataset(tmp_path).cameras[0].distortion.k1 == 0.3


@pytest.mark.skipif(not (SHARED_DATASETS / "fox" / "transforms.json").exists(), reason="needs ../shared/datasets/fox")
def test_instant_ngps_fox_loads_with_its_lens():
    ds = load_dataset(SHARED_DATASETS / "fox", downscale=4, load_images=False)
    lens = ds.cameras[0].distortion
    assert len(ds) == 60 and lens.model == "opencv" and lens.k1 == pytest.approx(0.0578421)
    assert (ds.cameras[0].width, ds.cameras[0].height) == (270, 480)


def test_a_distorted_capture_evaluates_like_its_pinhole_original(sphere_nerf, tmp_path):
    """Photos through a strong radial-tangential lens (rendered exactly, by an inverse written apart
    from the engine's): the NeRF trained on pinhole images scores on them as on pinhole ones when
    the rays go through the distorted pixels, and clearly worse when the lens is ignored."""
    import subprocess
    import sys

    from fixtures.sphere_data import write_distorted_sphere_dataset, write_sphere_dataset

    ckpt, _data = sphere_nerf
    # Strong enough to move the sphere's silhouette by about 2 pixels (it sits near the image centre).
    lens = {"k1": 1.5, "k2": 0.5, "p1": 0.02, "p2": -0.015}
    distorted = write_distorted_sphere_dataset(tmp_path / "distorted", **lens, n_views=6, size=64)
    pinhole = write_sphere_dataset(tmp_path / "pinhole", n_views=6, size=64)
    meta = json.loads((distorted / "transforms.json").read_text())
    for key in lens:
        meta.pop(key)
    ignored = tmp_path / "ignored"
    ignored.mkdir()
    (ignored / "images").symlink_to(distorted / "images")
    (ignored / "transforms.json").write_text(json.dumps(meta))

    def score(folder):
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "blender_nerf_deform.engine",
                "eval",
                "--nerf",
                str(ckpt),
                "--data",
                str(folder),
                "--device",
                "cpu",
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        return float(proc.stdout.strip().splitlines()[-1].split()[1])

    with_lens, without, plain = score(distorted), score(ignored), score(pinhole)
    # Measured: 20.4 dB through the lens, 21.7 pinhole, 16.1 with the lens ignored. The remaining
    # gap is the pixels' footprints: the lens stretches the periphery, where this 300-step NeRF
    # (trained at 32 px) is blurred differently.
    assert abs(with_lens - plain) < 1.5 and with_lens > without + 3.0, (with_lens, plain, without)
