"""Rendering: camera convention, chunk independence, occupancy and the ray-bending hooks, checkpoints."""

import math

import numpy as np
import pytest
import torch
from fixtures.ball_model import ball_model
from fixtures.sphere_data import look_at

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.nerf.checkpoint import load_nerf, save_nerf
from blender_nerf_deform.engine.nerf.occupancy import OccupancyGrid
from blender_nerf_deform.engine.nerf.renderer import Camera, camera_rays, render_image, render_rays


def _model(seed=0):
    """The ball of radius ~0.6 (fixtures.ball_model), its occupancy neither empty nor full."""
    m = ball_model(seed)
    assert 0 < int(m.occupancy.mask.sum()) < m.occupancy.mask.numel() // 4
    return m


def _camera(size=24):
    return Camera.from_fov(look_at((0.3, -3.5, 1.2)), size, size, 0.8, name="cam")


def test_camera_rays_follow_the_blender_convention():
    cam = Camera(np.eye(4), fx=2.0, fy=4.0, cx=2.0, cy=1.0, width=4, height=2)
    o, d = camera_rays(cam)
    assert o.shape == (8, 3) and torch.all(o == 0)
    # Pixel (i=0, j=0) is top-left: direction ((0.5-2)/2, -(0.5-1)/4, -1), normalised.
    want = torch.tensor([-0.75, 0.125, -1.0])
    assert torch.allclose(d[0], want / want.norm(), atol=1e-6)
    # Row-major: index 1 is pixel (i=1, j=0); index 4 is (i=0, j=1).
    assert torch.allclose(d[1], torch.tensor([-0.25, 0.125, -1.0]) / math.sqrt(0.0625 + 0.015625 + 1), atol=1e-6)
    assert d[4, 1] < 0  # the second row looks down (+Y up)
    # A rotated, translated camera: rays start at its position and turn with it.
    c2w = look_at((0.0, -4.0, 0.0))
    o, d = camera_rays(Camera.from_fov(c2w, 3, 3, 0.5))
    assert torch.allclose(o[4], torch.tensor([0.0, -4.0, 0.0]), atol=1e-6)
    assert torch.allclose(d[4], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)  # centre pixel looks at the origin


def test_rendering_does_not_depend_on_chunk_size():
    m = _model()
    o, d = camera_rays(_camera(), device=m.device)
    with torch.no_grad():
        a = render_rays(m, o, d, chunk=7)
        b = render_rays(m, o, d, chunk=100000)
    assert a["alpha"].max() > 0.5 and a["alpha"].min() < 0.01  # something and nothing in view
    for key in ("rgb", "alpha", "depth", "color"):
        assert torch.allclose(a[key], b[key], atol=1e-6), key
    assert a["n_density_samples"] == b["n_density_samples"]


def test_render_image_rgba_is_straight_alpha_and_matches_render_rays():
    m = _model()
    cam = _camera()
    img = render_image(m, cam, background=(0.0, 1.0, 0.0))
    assert img["rgba"].shape == (24, 24, 4) and img["depth"].shape == (24, 24)
    o, d = camera_rays(cam)
    with torch.no_grad():
        ref = render_rays(m, o, d, background=(0.0, 1.0, 0.0))
    a = img["rgba"][..., 3:]
    np.testing.assert_allclose(
        img["rgba"][..., :3] * a + (1 - a) * np.array([0, 1, 0]), ref["rgb"].numpy().reshape(24, 24, 3), atol=1e-5
    )
    hit = a[..., 0] > 0.5
    assert hit.any() and (img["depth"][hit] > 1.0).all() and (img["depth"][hit] < 6.0).all()
    assert img["density_samples_per_ray"] >= img["color_samples_per_ray"] > 0


def test_empty_occupancy_and_the_sample_transform_hook():
    m = _model()
    o, d = camera_rays(_camera())
    with torch.no_grad():
        base = render_rays(m, o, d)
        empty = OccupancyGrid.from_mask(m.aabb, torch.zeros(8, 8, 8, dtype=torch.bool))
        assert render_rays(m, o, d, occupancy=empty)["alpha"].abs().max() == 0
        full = OccupancyGrid.from_mask(m.aabb, torch.ones(8, 8, 8, dtype=torch.bool))
        assert render_rays(m, o, d, occupancy=full)["alpha"].sum() > 0
        calls = []

        def identity(p, v):
            calls.append(p.shape[0])
            return p, v, torch.ones(p.shape[0], dtype=torch.bool)

        same = render_rays(m, o, d, sample_transform=identity)
        assert calls and torch.allclose(same["rgb"], base["rgb"], atol=1e-6)
        dropped = render_rays(m, o, d, sample_transform=lambda p, v: (p, v, torch.zeros(p.shape[0], dtype=torch.bool)))
        assert dropped["alpha"].abs().max() == 0

        def shift(p, v):  # looking up the field 0.3 further along +x moves the picture
            return p + torch.tensor([0.3, 0.0, 0.0]), v, torch.ones(p.shape[0], dtype=torch.bool)

        moved = render_rays(m, o, d, sample_transform=shift, occupancy=full)
        assert not torch.allclose(moved["rgb"], base["rgb"], atol=1e-3)


def test_training_mode_rendering_is_differentiable_and_agrees_with_inference():
    m = _model()
    o, d = camera_rays(_camera(12))
    out = render_rays(m, o, d)
    out["rgb"].sum().backward()
    assert m.encoding.table.grad is not None and m.encoding.table.grad.abs().sum() > 0
    assert m.color_net[0].weight.grad.abs().sum() > 0
    with torch.no_grad():
        inf = render_rays(m, o, d)
    assert torch.allclose(out["rgb"].detach(), inf["rgb"], atol=2e-3)


def test_substeps_march_a_finer_step_that_converges():
    """`substeps` S marches the frame at the render step / S (a bent frame's own step too), and finer
    marches converge: 4 substeps are closer to 8 than one is. Bad values get one clear error."""
    m = _model()
    cam = _camera()
    frames = {s: render_image(m, cam, substeps=s) for s in (1, 2, 4, 8)}
    half = render_image(m, cam, step=m.config.render_step / 2)
    assert np.array_equal(frames[2]["rgba"], half["rgba"]) and np.array_equal(frames[2]["depth"], half["depth"])
    assert frames[2]["density_samples_per_ray"] > 1.8 * frames[1]["density_samples_per_ray"]
    quarter = render_image(m, cam, step=m.config.render_step / 2, substeps=2)  # a given step is divided too
    assert np.array_equal(quarter["rgba"], frames[4]["rgba"])
    error = {s: np.abs(frames[s]["rgba"] - frames[8]["rgba"]).mean() for s in (1, 4)}
    assert error[4] < 0.5 * error[1], error
    for bad in (0, 17, 1.5, True, "2"):
        with pytest.raises(EngineError, match="substeps"):
            render_image(m, cam, substeps=bad)


def test_checkpoint_round_trip_renders_identical_pixels(tmp_path):
    m = _model(seed=3)
    path = tmp_path / "nerf.ckpt"
    save_nerf(m, path)
    assert [p.name for p in tmp_path.iterdir()] == ["nerf.ckpt"]  # no temporary left behind
    loaded = load_nerf(path, device="cpu")
    assert loaded.config == m.config and torch.equal(loaded.occupancy.mask, m.occupancy.mask)
    a = render_image(m, _camera())
    b = render_image(loaded, _camera())
    assert np.array_equal(a["rgba"], b["rgba"]) and np.array_equal(a["depth"], b["depth"])


def test_bad_checkpoints_get_one_clear_error(tmp_path):
    m = _model()
    good = tmp_path / "good.ckpt"
    save_nerf(m, good)
    data = good.read_bytes()
    cases = {
        "missing.ckpt": None,
        "truncated.ckpt": data[: len(data) // 2],
        "corrupt.ckpt": data[:200] + bytes(1000) + data[1200:],
        "foreign.ckpt": b"PK\x03\x04 this is not a checkpoint",
        "text.ckpt": b"hello",
    }
    for name, content in cases.items():
        p = tmp_path / name
        if content is not None:
            p.write_bytes(content)
        with pytest.raises(EngineError) as exc:
            load_nerf(p, device="cpu")
        msg = str(exc.value)
        assert name in msg and "\n" not in msg, msg
    other = tmp_path / "other.ckpt"
    torch.save({"weights": torch.zeros(3)}, other)  # a real torch file, but not ours
    with pytest.raises(EngineError, match="not a blender_nerf_deform NeRF checkpoint"):
        load_nerf(other, device="cpu")
    versioned = tmp_path / "future.ckpt"
    payload = torch.load(good, weights_only=True)
    payload["version"] = 99
    torch.save(payload, versioned)
    with pytest.raises(EngineError, match="version 99"):
        load_nerf(versioned, device="cpu")


def test_cuda_without_cuda_is_a_clear_error(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    save_nerf(_model(), tmp_path / "n.ckpt")
    with pytest.raises(EngineError, match="--device cuda"):
        load_nerf(tmp_path / "n.ckpt", device="cuda")


def test_an_interrupted_save_leaves_the_previous_checkpoint_whole(tmp_path, monkeypatch):
    m = _model()
    path = tmp_path / "nerf.ckpt"
    save_nerf(m, path)
    before = path.read_bytes()

    def torch_save_then_die(obj, f, *a, **k):
        f.write(b"half a checkpoint")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", torch_save_then_die)
    with pytest.raises(KeyboardInterrupt):
        save_nerf(m, path)
    monkeypatch.undo()
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["nerf.ckpt"]
    assert torch.equal(load_nerf(path, device="cpu").encoding.table, m.encoding.table)
