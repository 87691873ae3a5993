"""Ray bending through real edits of the sphere NeRF: a part moved, the object widened, tets turned inside
out, a slow animation, and `render --deformed DIR` end to end. The sphere (radius 0.8 at the origin) is the
analytic one of nerf_fixtures, trained briefly."""

import json
from dataclasses import replace

import numpy as np
import pytest
from fixtures.sphere_data import RADIUS, look_at

from blender_nerf_deform.engine.geometry.cage import box_cage
from blender_nerf_deform.engine.nerf.substeps import FINAL_SUBSTEPS


def _psnr(a, b):
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


@pytest.fixture(scope="module")
def model(sphere_nerf):
    from blender_nerf_deform.engine.nerf.checkpoint import load_nerf

    return load_nerf(sphere_nerf[0], device="cpu")


def _camera(eye, size, angle, target=(0.0, 0.0, 0.0)):
    from blender_nerf_deform.engine.nerf.renderer import Camera

    return Camera.from_fov(look_at(eye, target), size, size, angle)


def _pixel(camera, point):
    """(row, column) of the pixel a world point projects to."""
    w2c = np.linalg.inv(camera.c2w)
    q = w2c[:3, :3] @ np.asarray(point, np.float64) + w2c[:3, 3]
    return int(camera.cy - camera.fy * q[1] / -q[2]), int(camera.cx + camera.fx * q[0] / -q[2])


def _premultiplied(rgba):
    """Colour times alpha: the straight colour of a nearly empty pixel is noise."""
    return np.concatenate([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], axis=-1)


def _render(model, camera, bend=None, substeps=1):
    from blender_nerf_deform.engine.nerf.renderer import render_image

    kw = {"sample_transform": bend.sample_transform, "occupancy": bend.occupancy} if bend else {}
    return render_image(model, camera, substeps=substeps, **kw)["rgba"]


# A distant, narrow camera looking along -x: rays nearly parallel, so heights in the image are heights in the scene.
FAR = dict(size=64, angle=0.36)


@pytest.mark.slow
def test_translating_a_part_empties_its_old_place_and_draws_it_at_the_new_one(model):
    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    camera = _camera((8.0, 0.0, 0.6), target=(0.0, 0.0, 0.6), **FAR)
    # A cage around the cap of the sphere above z = 0.3 only; lifted by 0.5, the rest of the sphere stays.
    rest, tets = box_cage((3, 3, 2), lo=(-0.9, -0.9, 0.3), hi=(0.9, 0.9, 0.9))
    lift = np.array([0.0, 0.0, 0.5])
    plain = _render(model, camera)
    bent = _render(model, camera, CageBend(model, rest, tets).set_deformed(rest + lift))

    def alpha(img, z):
        return img[_pixel(camera, (0.0, 0.0, z))][3]

    # Old place (0.35 <= z <= 0.75): full before, empty after; the lower sphere is untouched. (Near the
    # cap's top the ray crosses little of it: at z = 0.7 a 300-step NeRF has given it 0.88 to 0.99,
    # depending on its training's random draws.)
    for z in (0.4, 0.55, 0.65):
        assert alpha(plain, z) > 0.9 and alpha(bent, z) < 0.05, z
    assert alpha(bent, 0.0) > 0.95 and alpha(bent, 0.2) > 0.95
    # New place: the cap now spans z = 0.8 .. 1.3 (the sphere's top, 0.8, lifted), sampled where the old
    # place was sampled, lifted (not at 1.2: the cap's fragile top edge, rest z 0.7, which this session's
    # fixture NeRF gave 0.86 at rest and 0.90 lifted; the PSNR check below compares the cap as a whole).
    for z in (0.9, 1.05, 1.15):
        assert alpha(plain, z) < 0.05 and alpha(bent, z) > 0.9, z
    assert alpha(bent, RADIUS + 0.5 + 0.15) < 0.05
    # And it is the cap itself: above z = 0.85 the frame equals the undeformed one seen from 0.5 lower.
    c2w = np.array(camera.c2w)
    c2w[:3, 3] -= lift
    moved_camera = _render(model, replace(camera, c2w=c2w))
    rows = slice(0, _pixel(camera, (0.0, 0.0, 0.85))[0])
    assert bent[rows, :, 3].sum() > 50
    assert _psnr(_premultiplied(bent[rows]), _premultiplied(moved_camera[rows])) >= 40


@pytest.mark.slow
def test_widening_along_one_axis_widens_the_silhouette_by_the_scale(model):
    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    camera = _camera((0.0, -8.0, 0.0), **FAR)  # image x = world x, image up = world z
    rest, tets = box_cage((4, 4, 4), lo=(-1.5,) * 3, hi=(1.5,) * 3)
    plain = _render(model, camera)[..., 3]
    wide = _render(model, camera, CageBend(model, rest, tets).set_deformed(rest * [1.3, 1.0, 1.0]))[..., 3]
    # Silhouette width: alpha summed along the widest row (sub-pixel); height: along the tallest column.
    assert plain.sum(1).max() > 25
    assert wide.sum(1).max() / plain.sum(1).max() == pytest.approx(1.3, abs=0.03)
    assert wide.sum(0).max() / plain.sum(0).max() == pytest.approx(1.0, abs=0.02)


@pytest.mark.slow
def test_inverted_tets_give_no_nan_and_no_hole(model):
    import torch

    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    # 1. A mirror of the whole cage turns every tet inside out; the sphere must come back whole:
    #    the mirrored scene from a camera is the plain scene from the mirrored camera, flipped left-right.
    rest, tets = box_cage((4, 4, 4), lo=(-1.5,) * 3, hi=(1.5,) * 3)
    camera = _camera((3.0, 0.5, 0.4), size=40, angle=0.9)
    bend = CageBend(model, rest, tets).set_deformed(rest * [-1.0, 1.0, 1.0])
    assert bend.inversion.n_inverted == len(tets)
    mirrored = _render(model, camera, bend)
    assert np.isfinite(mirrored).all()
    c2w = np.array(camera.c2w)
    c2w[0, :] *= -1  # mirror the camera's position and axes in x ...
    c2w[:, 0] *= -1  # ... and keep it right-handed (its own x flips: the image is flipped left-right)
    expected = _render(model, replace(camera, c2w=c2w))[:, ::-1]
    assert expected[..., 3].sum() > 100
    assert _psnr(mirrored[..., 3], expected[..., 3]) >= 35

    # 2. One vertex just inside the front of the sphere pushed through the face opposite it: a fold at the
    #    surface the camera sees. Alpha stays ~1 there and every sample in the folded region maps somewhere.
    rest, tets = box_cage((6, 6, 6), lo=(-1.5,) * 3, hi=(1.5,) * 3)
    v = int(np.argmin(np.linalg.norm(rest - [0.5, 0.0, 0.0], axis=1)))
    star = tets[(tets == v).any(1)]
    deformed = rest.copy()
    deformed[v] = [1.1, 0.05, 0.05]  # beyond the star's far side (x = 1.0)
    bend = CageBend(model, rest, tets).set_deformed(deformed)
    assert 1 <= bend.inversion.n_inverted < len(star)
    camera = _camera((3.0, 0.0, 0.0), size=40, angle=0.9)
    plain, folded = _render(model, camera), _render(model, camera, bend)
    assert np.isfinite(folded).all()
    r, c = _pixel(camera, (0.8, 0.0, 0.0))
    window = (slice(r - 3, r + 4), slice(c - 3, c + 4))
    assert plain[window][..., 3].min() > 0.95
    assert folded[window][..., 3].min() > 0.95
    pts = torch.as_tensor(
        np.random.default_rng(0).uniform(deformed[star].min((0, 1)), deformed[star].max((0, 1)), (20000, 3)),
        dtype=torch.float32,
    )
    p, d, _keep, *_ = bend.sample_transform(pts, torch.nn.functional.normalize(pts, dim=1))
    assert torch.isfinite(p).all() and torch.isfinite(d).all()
    assert (bend.deformed.locate(pts) >= 0).all()  # inside the box cage: no sample falls through the fold


@pytest.mark.slow
def test_a_slow_twist_renders_consecutive_frames_that_differ_smoothly(model):
    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    def twist(V, rate):
        a = rate * V[:, 2]
        c, s = np.cos(a), np.sin(a)
        return np.stack([c * V[:, 0] - s * V[:, 1], s * V[:, 0] + c * V[:, 1], V[:, 2]], axis=1)

    rest, tets = box_cage((6, 6, 6), lo=(-1.5,) * 3, hi=(1.5,) * 3)
    camera = _camera((3.0, 0.0, 0.0), size=48, angle=0.9)
    bend = CageBend(model, rest, tets)  # one cage, posed per frame
    frames = [_render(model, camera, bend.set_deformed(twist(rest, 0.05 * k))) for k in range(7)]
    step = np.array([np.abs(frames[k + 1] - frames[k]).mean() for k in range(6)])
    # Equal pose steps give about equal frame changes: no frame jumps out (what rebuilt topology would do).
    # The trend along the twist depends on the session's fixture NeRF (measured 0.0051-0.0077 one session,
    # 0.0047-0.0080 another, ratio 1.5-1.7), so the checks are a spike above both neighbours and a loose spread.
    assert step.min() > 0.002
    print("frame steps", np.round(step, 5))
    for k in range(1, len(step) - 1):
        assert step[k] < 1.5 * 0.5 * (step[k - 1] + step[k + 1]), f"frame {k + 1} jumps out: {np.round(step, 5)}"
    assert step.max() / step.min() < 2.0
    # And the change grows with the pose step.
    from_first = [np.abs(frames[k] - frames[0]).mean() for k in range(1, 4)]
    assert from_first[0] < from_first[1] < from_first[2]
    assert 1.3 < from_first[1] / from_first[0] < 2.3


def _cli(*args):
    import subprocess
    import sys

    from fixtures import REPO

    return subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", *map(str, args)], cwd=REPO, capture_output=True, text=True
    )


@pytest.mark.slow
def test_cli_renders_an_animation_from_a_folder_of_poses(sphere_nerf, model, tmp_path):
    from PIL import Image

    from blender_nerf_deform.engine.bend.cage_bend import CageBend
    from blender_nerf_deform.engine.geometry.mesh_io import save_cage
    from blender_nerf_deform.engine.nerf.renderer import Camera

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    # One still camera, three frames (the file names are the frames' names), a cap lifted a little more each frame.
    frames = [
        {"file_path": f"shot/f{k:02d}", "transform_matrix": meta["frames"][4]["transform_matrix"]} for k in range(3)
    ]
    (tmp_path / "cams.json").write_text(
        json.dumps({"camera_angle_x": meta["camera_angle_x"], "w": 32, "h": 32, "frames": frames})
    )
    rest, tets = box_cage((2, 2, 2), lo=(-0.9, -0.9, 0.3), hi=(0.9, 0.9, 0.9))
    save_cage(tmp_path / "cage.npz", rest, tets)
    poses = tmp_path / "poses"
    poses.mkdir()
    lifts = [0.0, 0.2, 0.4]
    # Natural order: pose_2 before pose_10, whatever the plain string order says.
    for name, lift in zip(("pose_1.npy", "pose_2.npy", "pose_10.npy"), lifts):
        np.save(poses / name, rest + [0.0, 0.0, lift])
    proc = _cli(
        "render",
        "--nerf",
        ckpt,
        "--cameras",
        tmp_path / "cams.json",
        "--out",
        tmp_path / "out",
        "--cage",
        tmp_path / "cage.npz",
        "--deformed",
        poses,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "frame f01: 0 inverted and 0 degenerate of 48 tets" in proc.stdout + proc.stderr
    bend = CageBend(model, rest, tets)
    camera = Camera.from_fov(np.array(frames[0]["transform_matrix"]), 32, 32, meta["camera_angle_x"])
    for k, lift in enumerate(lifts):
        got = np.asarray(Image.open(tmp_path / "out" / f"f{k:02d}.png"), dtype=np.float64) / 255
        want = _render(model, camera, bend.set_deformed(rest + [0.0, 0.0, lift]), substeps=FINAL_SUBSTEPS)
        assert _psnr(got, want) >= 40, k
    first, last = (np.asarray(Image.open(tmp_path / "out" / f"f{k:02d}.png"), dtype=np.float64) for k in (0, 2))
    assert _psnr(first, last) < 30  # the frames did follow their poses

    def error(*extra):
        out = _cli(
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
            *extra,
        )
        assert out.returncode == 2, out.stderr
        return out.stderr

    (poses / "pose_11.npy").write_bytes((poses / "pose_10.npy").read_bytes())
    assert "4 pose files (.npy) for 3 camera frames" in error(poses)
    (poses / "pose_11.npy").unlink()
    np.save(poses / "pose_2.npy", np.r_[rest, rest[:1]])
    assert "pose_2.npy: deformed vertices must be a finite (27, 3) array" in error(poses)
    assert "28 vertices, the cage has 27" in error(poses)
    nan = rest.copy()
    nan[5, 1] = np.nan
    np.save(poses / "pose_2.npy", nan)
    assert "pose_2.npy" in error(poses) and "NaN or inf (first: vertex 5)" in error(poses)
    np.save(poses / "pose_2.npy", rest.reshape(-1))
    assert "pose_2.npy: deformed vertices must be a finite (27, 3) array" in error(poses)
    assert not (tmp_path / "bad").exists()  # checked before anything is rendered


def test_the_cpu_kernels_and_the_torch_path_agree(model):
    """The torch path is what CUDA runs: same deformed occupancy and same samples as the numba kernels."""
    import torch

    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    rest, tets = box_cage((5, 5, 5), lo=(-1.2,) * 3, hi=(1.2,) * 3)
    a = 0.4 * np.clip(rest[:, 2], 0, None)  # twist the upper half
    posed = np.stack(
        [
            np.cos(a) * rest[:, 0] - np.sin(a) * rest[:, 1],
            np.sin(a) * rest[:, 0] + np.cos(a) * rest[:, 1],
            rest[:, 2] + 0.1,
        ],
        axis=1,
    )
    pts = torch.as_tensor(np.random.default_rng(1).uniform(-1.4, 1.4, (50000, 3)), dtype=torch.float32)
    dirs = torch.nn.functional.normalize(
        torch.as_tensor(np.random.default_rng(2).normal(size=(50000, 3)), dtype=torch.float32), dim=1
    )
    results = []
    from blender_nerf_deform.engine import backend

    for path in ("auto", "torch"):  # the whole bender on one path: its kernels and its point location
        with backend.forced(path):
            bend = CageBend(model, rest, tets)
            assert bend.use_kernels == (path == "auto") and bend.rest.backend == (
                "numba" if path == "auto" else "torch"
            )
            bend.set_deformed(posed)
            results.append((bend.occupancy.aabb, bend.occupancy.mask, *bend.sample_transform(pts, dirs)))
    (box_k, mask_k, p_k, d_k, keep_k, s_k), (box_t, mask_t, p_t, d_t, keep_t, s_t) = results
    assert torch.equal(box_k, box_t)
    # The NeRF grid's cell corners lie on this box cage's faces, where the two locators may pick
    # different tets (measured: 8 of ~194,500 marked cells differ); both images are valid.
    assert int((mask_k != mask_t).sum()) <= 1e-4 * int(mask_k.sum())
    assert mask_k.any() and keep_k.any() and not keep_k.all()
    assert torch.allclose(p_k, p_t, atol=1e-5)  # the map is continuous across tet faces
    # A view direction turns with its tet, which is discontinuous across faces: the two point
    # locators (float32 torch, float64 numba) may pick either tet for a sample on a face.
    turned = (d_k - d_t).abs().amax(dim=1) > 1e-5
    assert int(turned.sum()) <= 5, int(turned.sum())
    assert (keep_k != keep_t).sum() <= 2  # a sample exactly on a cell face may round either way
    # The density scale (rest-space length of a unit step along the ray) is per tet, like the direction.
    assert s_k.shape == s_t.shape == (len(pts),) and (s_k != 1).any()
    assert int(((s_k - s_t).abs() > 1e-5).sum()) <= 5
