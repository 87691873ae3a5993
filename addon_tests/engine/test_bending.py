"""Ray bending through a cage: identity is invisible, a rigid move of the whole cage equals moving the
camera the other way, vacated space is empty, degenerate tets give no NaN."""

import json

import numpy as np
import pytest

from blender_nerf_deform.engine.geometry.cage import box_cage


def _psnr(a, b):
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


@pytest.fixture(scope="module")
def scene(sphere_nerf):
    from blender_nerf_deform.engine.nerf.checkpoint import load_nerf
    from blender_nerf_deform.engine.nerf.renderer import Camera

    ckpt, data = sphere_nerf
    model = load_nerf(ckpt, device="cpu")
    meta = json.loads((data / "transforms.json").read_text())
    c2w = np.array(meta["frames"][4]["transform_matrix"])
    camera = Camera.from_fov(c2w, 40, 40, meta["camera_angle_x"])
    # A cage over the NeRF's whole box: everything the NeRF holds is inside it.
    rest, tets = box_cage((4, 4, 4), lo=(-1.5, -1.5, -1.5), hi=(1.5, 1.5, 1.5))
    return model, camera, rest, tets


def _render(model, camera, bend=None):
    from blender_nerf_deform.engine.nerf.renderer import render_image

    kw = {"sample_transform": bend.sample_transform, "occupancy": bend.occupancy} if bend else {}
    return render_image(model, camera, **kw)["rgba"]


@pytest.mark.slow
def test_identity_deformation_reproduces_the_undeformed_render(scene):
    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    model, camera, rest, tets = scene
    plain = _render(model, camera)
    bent = _render(model, camera, CageBend(model, rest, tets).set_deformed(rest))
    assert plain[..., 3].max() > 0.4
    assert _psnr(bent, plain) >= 50


@pytest.mark.slow
def test_moving_the_whole_cage_equals_moving_the_camera_back(scene):
    from dataclasses import replace

    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    model, camera, rest, tets = scene
    shift = np.array([0.3, -0.2, 0.25])
    bend = CageBend(model, rest, tets).set_deformed(rest + shift)
    moved_content = _render(model, camera, bend)
    c2w = np.array(camera.c2w, dtype=np.float64)
    c2w[:3, 3] -= shift
    moved_camera = _render(model, replace(camera, c2w=c2w))
    assert _psnr(moved_content, moved_camera) >= 40
    assert _psnr(moved_content, _render(model, camera)) < 30  # it did move


def test_degenerate_and_inverted_tets_give_finite_maps_and_are_counted(scene):
    import torch

    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    model, camera, rest, tets = scene
    deformed = rest.copy()
    a, b, c, d = tets[0]
    deformed[d] = (deformed[a] + deformed[b] + deformed[c]) / 3  # flatten one tet (degenerate)
    bend = CageBend(model, rest, tets).set_deformed(deformed)
    assert bend.inversion.n_degenerate >= 1
    assert (
        torch.isfinite(bend.linear).all() and torch.isfinite(bend.offset).all() and torch.isfinite(bend.rotation).all()
    )
    pts = torch.as_tensor(np.random.default_rng(0).uniform(-1.5, 1.5, (5000, 3)), dtype=torch.float32)
    p, d_out, keep, *_ = bend.sample_transform(pts, torch.nn.functional.normalize(pts, dim=1))
    assert torch.isfinite(p).all() and torch.isfinite(d_out).all()


def _cli(*args):
    import subprocess
    import sys

    from fixtures import REPO

    return subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", *map(str, args)], cwd=REPO, capture_output=True, text=True
    )


@pytest.mark.slow
def test_cli_render_through_a_cage(sphere_nerf, tmp_path):
    from PIL import Image

    from blender_nerf_deform.engine.geometry.mesh_io import save_cage

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    (tmp_path / "cams.json").write_text(json.dumps({**meta, "frames": meta["frames"][:1]}))
    rest, tets = box_cage((3, 3, 3), lo=(-1.5, -1.5, -1.5), hi=(1.5, 1.5, 1.5))
    save_cage(tmp_path / "cage.npz", rest, tets)
    np.save(tmp_path / "rest.npy", rest)
    np.save(tmp_path / "lifted.npy", rest + [0.0, 0.0, 0.4])
    name = meta["frames"][0]["file_path"].rsplit("/", 1)[-1].rsplit(".", 1)[0]

    def render(*extra):
        out = tmp_path / f"out{len(list(tmp_path.iterdir()))}"
        proc = _cli("render", "--nerf", ckpt, "--cameras", tmp_path / "cams.json", "--out", out, *extra)
        assert proc.returncode == 0, proc.stderr[-2000:]
        return np.asarray(Image.open(out / f"{name}.png"), dtype=np.float64) / 255

    plain = render()
    assert _psnr(render("--cage", tmp_path / "cage.npz", "--deformed", tmp_path / "rest.npy"), plain) >= 45
    assert _psnr(render("--cage", tmp_path / "cage.npz", "--deformed", tmp_path / "lifted.npy"), plain) < 30

    np.save(tmp_path / "wrong.npy", rest[:5])
    proc = _cli(
        "render",
        "--nerf",
        ckpt,
        "--cameras",
        tmp_path / "cams.json",
        "--out",
        tmp_path / "bad",
        "--cage",
        tmp_path / "cage.npz",
        "--deformed",
        tmp_path / "wrong.npy",
    )
    assert proc.returncode == 2 and "wrong.npy: deformed vertices must be a finite (64, 3) array" in proc.stderr
