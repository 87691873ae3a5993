"""Training learns: a CI-sized run on a tiny analytic dataset beats the best constant colour by a clear
margin; the command line trains, resumes, evaluates and renders; interrupted checkpoints stay whole."""

import re
import subprocess
import sys

import numpy as np
import pytest
import torch
from fixtures import REPO
from fixtures.sphere_data import write_sphere_dataset
from PIL import Image

from blender_nerf_deform.engine.nerf.checkpoint import load_nerf
from blender_nerf_deform.engine.nerf.dataset import load_dataset
from blender_nerf_deform.engine.nerf.evaluate import evaluate, psnr
from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
from blender_nerf_deform.engine.nerf.renderer import render_image
from blender_nerf_deform.engine.nerf.substeps import FINAL_SUBSTEPS
from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions

SMALL = {"log2_table_size": 14, "finest_resolution": 128, "occ_resolution": 32, "steps_per_diagonal": 256}


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    root = tmp_path_factory.mktemp("sphere")
    train = write_sphere_dataset(root / "train", n_views=30, size=32, seed=0)
    test = write_sphere_dataset(root / "test", n_views=5, size=32, seed=7)
    return train, test


def _constant_baseline_psnr(train, test) -> float:
    """PSNR of the best constant colour (the training images' mean on white) on the test views."""
    on_white = lambda im: im[..., :3] * im[..., 3:] + (1 - im[..., 3:])  # noqa: E731
    mean = on_white(train.images).reshape(-1, 3).mean(0)
    return float(np.mean([psnr(np.broadcast_to(mean, im.shape[:2] + (3,)), on_white(im)) for im in test.images]))


@pytest.mark.slow
def test_training_beats_the_constant_colour_baseline(tmp_path):
    # A small subset, downsampled: 30 views of 64x64 trained at 32x32 (--downscale 2).
    train = load_dataset(write_sphere_dataset(tmp_path / "train", n_views=30, size=64, seed=0), downscale=2)
    test = load_dataset(write_sphere_dataset(tmp_path / "test", n_views=5, size=64, seed=7), downscale=2)
    assert train.images.shape == (30, 32, 32, 4)
    torch.manual_seed(0)
    model = NerfModel(NerfConfig(aabb=train.aabb.reshape(-1).tolist(), **SMALL))
    trainer = Trainer(model, train, TrainOptions(steps=250, target_samples=1 << 13, occ_warmup_steps=64))
    summary = trainer.train(progress=False)
    assert summary["steps"] == 250
    baseline = _constant_baseline_psnr(train, test)
    got = float(np.mean(evaluate(model.eval(), test)))
    print(f"constant colour {baseline:.2f} dB, NeRF {got:.2f} dB")
    assert baseline < 15.0
    assert got > baseline + 10.0, (got, baseline)
    assert got > 22.0
    # The occupancy grid learned the ball: far corners are empty, the centre is occupied.
    occ = model.occupancy.occupied(torch.tensor([[0.0, 0.0, 0.0], [1.4, 1.4, 1.4], [-1.4, 1.4, -1.4]]))
    assert occ.tolist() == [True, False, False]


@pytest.mark.slow
def test_the_torch_path_that_cuda_runs_trains_like_the_kernels(sphere, monkeypatch):
    """Encoding, marching and Adam without the numba kernels (the code CUDA runs), on CPU: same samples,
    and the same training gets about the same quality."""
    from blender_nerf_deform.engine import backend
    from blender_nerf_deform.engine.nerf import renderer

    if not backend.HAVE_NUMBA:
        pytest.skip("numba is not installed: every test already runs the torch path")
    train = load_dataset(sphere[0])
    views = train.subset(range(3))
    results = {}
    for kernels in (True, False):
        monkeypatch.setattr(backend, "_path", "auto" if kernels else "torch")
        torch.manual_seed(0)
        model = NerfModel(NerfConfig(aabb=train.aabb.reshape(-1).tolist(), **SMALL))
        model.occupancy.update(model.density, model.config.render_step, model.config.occ_threshold)
        o, d = renderer.camera_rays(train.cameras[0])
        results[kernels, "march"] = renderer.march(o, d, model.occupancy, model.config.render_step)
        before = float(np.mean(evaluate(model.eval(), views)))
        trainer = Trainer(model, train, TrainOptions(steps=100, target_samples=1 << 12, occ_warmup_steps=32))
        assert trainer.lazy_table == kernels
        trainer.train(progress=False)
        results[kernels] = (before, float(np.mean(evaluate(model.eval(), views))))
    fast, slow = results[True, "march"], results[False, "march"]
    # Same samples, but for the odd one on a cell face (the two round differently).
    assert fast[0].numel() > 1000 and abs(fast[0].numel() - slow[0].numel()) <= 0.002 * fast[0].numel()
    if fast[0].numel() == slow[0].numel():
        assert torch.equal(fast[0], slow[0]) and torch.allclose(fast[1], slow[1], atol=1e-5)
    (before_k, after_k), (before_t, after_t) = results[True], results[False]
    assert before_k == pytest.approx(before_t, abs=1e-3)
    assert after_t > before_t + 3.0 and abs(after_t - after_k) < 2.5, results


def _cli(*args, check=True):
    proc = subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if check:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.mark.slow
def test_cli_train_resume_eval_render(sphere, tmp_path):
    train_dir, test_dir = sphere
    run = tmp_path / "run"
    _cli("train", "--data", train_dir, "--out", run, "--steps", "40", "--device", "cpu")
    ckpt = run / "nerf.ckpt"
    assert ckpt.is_file() and [p.name for p in run.iterdir() if p.suffix == ".tmp"] == []
    first = load_nerf(ckpt, device="cpu")
    proc = _cli("train", "--data", train_dir, "--out", run, "--steps", "60", "--resume")
    assert "trained 60 steps" in proc.stdout  # 40 resumed + 20 more
    second = load_nerf(ckpt, device="cpu")
    assert not torch.equal(first.encoding.table, second.encoding.table)

    proc = _cli("eval", "--nerf", ckpt, "--data", test_dir)
    mean = float(re.search(r"PSNR ([0-9.]+) dB over 5 frames", proc.stdout).group(1))
    assert 10.0 < mean < 60.0

    out = tmp_path / "frames"
    _cli("render", "--nerf", ckpt, "--cameras", test_dir / "transforms.json", "--out", out)
    names = sorted(p.name for p in out.iterdir())
    assert names == [f"r_{k}.png" for k in range(5)]
    with Image.open(out / "r_0.png") as im:
        assert im.mode == "RGBA" and im.size == (32, 32)
        a = np.asarray(im)[..., 3]
    assert a.max() > 100 and a.min() < 30  # the ball (60 steps: not yet opaque), and empty space around it
    # Final frames march FINAL_SUBSTEPS samples per step; --substeps 1 is a preview's march.
    one = tmp_path / "one"
    _cli("render", "--nerf", ckpt, "--cameras", test_dir / "transforms.json", "--out", one, "--substeps", "1")
    camera = load_dataset(test_dir).cameras[0]
    for folder, substeps in ((out, FINAL_SUBSTEPS), (one, 1)):
        with Image.open(folder / "r_0.png") as im:
            written = np.asarray(im).astype(int)
        want = np.round(render_image(second, camera, substeps=substeps)["rgba"] * 255).astype(int)
        assert np.abs(written - want).max() <= 1, substeps
    with Image.open(one / "r_0.png") as im_one, Image.open(out / "r_0.png") as im_final:
        assert not np.array_equal(np.asarray(im_one), np.asarray(im_final))
    for bad in ("0", "17", "nan", "1.5"):  # each refused by the argument parser, before torch loads
        proc = _cli(
            "render",
            "--nerf",
            ckpt,
            "--cameras",
            test_dir / "transforms.json",
            "--out",
            one,
            "--substeps",
            bad,
            check=False,
        )
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert "argument --substeps: " in proc.stderr and bad in proc.stderr.splitlines()[-1], proc.stderr

    half = tmp_path / "half"
    _cli("render", "--nerf", ckpt, "--cameras", test_dir / "transforms.json", "--out", half, "--downscale", "2")
    with Image.open(half / "r_0.png") as im:
        assert im.size == (16, 16)

    proc = _cli(
        "render",
        "--nerf",
        ckpt,
        "--cameras",
        test_dir / "transforms.json",
        "--out",
        out,
        "--cage",
        tmp_path / "c.npz",
        "--deformed",
        tmp_path / "v.npy",
        check=False,
    )
    assert (
        proc.returncode == 2
        and proc.stderr.strip().splitlines()[-1] == f"error: cage file {tmp_path / 'c.npz'} does not exist"
    )
    proc = _cli(
        "render",
        "--nerf",
        ckpt,
        "--cameras",
        test_dir / "transforms.json",
        "--out",
        out,
        "--cage",
        tmp_path / "c.npz",
        check=False,
    )
    assert proc.returncode == 2 and "--cage and --deformed go together" in proc.stderr


def test_cli_device_cuda_without_cuda(sphere, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    proc = _cli("train", "--data", sphere[0], "--out", tmp_path / "r", "--steps", "1", "--device", "cuda", check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith("error: --device cuda")


def test_an_occupancy_update_keeps_the_largest_of_a_cells_repeated_samples():
    """Random cells repeat within one update, each at its own jittered point: the cell keeps the max
    (as an EMA-max should), whatever order the writes land in."""
    from blender_nerf_deform.engine.nerf.occupancy import OccupancyGrid

    grid = OccupancyGrid(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), resolution=4)
    grid.density = torch.linspace(0.0, 6.3, 64)
    before = grid.density.clone()
    seen = []

    def density(points):  # depends on where in its cell each point landed
        seen.append(points.clone())
        return 5.0 + 3.0 * points.sum(-1)

    torch.manual_seed(3)
    grid.update(density, step_size=0.1, decay=0.95, n_uniform=3000, n_occupied=0)
    pts = torch.cat(seen)
    cells = ((pts - grid.aabb[0]) / grid.cell_size).floor().long()
    idx = cells[:, 0] + 4 * cells[:, 1] + 16 * cells[:, 2]
    assert np.bincount(idx.numpy(), minlength=64).min() > 20  # every cell was drawn many times
    expected = before.clone()
    for c in range(64):
        expected[c] = max(float(before[c]) * 0.95, float(density(pts[idx == c]).max()))
    assert torch.allclose(grid.density, expected, rtol=0, atol=1e-6)


def test_error_map_draws_rays_where_the_error_is_and_follows_the_loss(tmp_path):
    """instant-ngp's error map: the share of rays it draws lands in tiles in proportion to their recorded
    error, inside the image where the last tiles are cut by its edge, and each tile's error follows the
    squared errors recorded for its pixels."""
    from blender_nerf_deform.engine.nerf.trainer import ERROR_TILE

    size = ERROR_TILE * 2 + 3  # the last row and column of tiles are 3 pixels wide
    ds = load_dataset(write_sphere_dataset(tmp_path / "s", n_views=2, size=size))
    trainer = Trainer(
        NerfModel(NerfConfig(aabb=ds.aabb.reshape(-1).tolist(), **SMALL)), ds, TrainOptions(steps=1, error_rays=1.0)
    )
    assert trainer.tile_error.shape == (2 * 3 * 3,) and bool((trainer.tile_error == 1).all())  # unvisited: high
    last = 2 * 3 * 3 - 1  # image 1's corner tile
    trainer.tile_error.fill_(1e-8)
    trainer.tile_error[last] = 1.0
    idx = trainer.draw_pixels(4000)
    img, y, x = idx // (size * size), (idx % (size * size)) // size, idx % size
    assert bool((img == 1).all()) and bool(((y >= 2 * ERROR_TILE) & (y < size)).all())
    assert bool(((x >= 2 * ERROR_TILE) & (x < size)).all())
    assert len(set(zip(y.tolist(), x.tolist()))) == 9  # every pixel of the 3x3 corner, none beyond it
    # Half the fraction: the other half is drawn uniformly over both images.
    trainer.opt.error_rays = 0.5
    img = trainer.draw_pixels(4000) // (size * size)
    assert 800 < int((img == 0).sum()) < 1200

    first = torch.tensor([0, 1, size])  # three pixels of image 0's first tile
    trainer.record_errors(first, torch.tensor([0.1, 0.2, 0.3]))
    assert trainer.tile_error[0].item() == pytest.approx(0.5 * 1e-8 + 0.5 * 0.2)
    assert trainer.tile_error[1].item() == pytest.approx(1e-8)  # untouched tiles keep theirs
    trainer.record_errors(torch.tensor([0]), torch.tensor([0.0]))
    assert trainer.tile_error[0].item() == pytest.approx(0.5 * (0.5 * 1e-8 + 0.5 * 0.2))
    assert torch.all(trainer.tile_error > 0)  # multinomial needs a positive total
    trainer.tile_error.fill_(1.0)
    trainer.step()  # a training step records its rays' errors
    assert 0 < int((trainer.tile_error < 1.0).sum()) and bool(torch.isfinite(trainer.tile_error).all())
    with pytest.raises(ValueError, match="error_rays"):
        Trainer(NerfModel(NerfConfig(aabb=ds.aabb.reshape(-1).tolist(), **SMALL)), ds, TrainOptions(error_rays=1.5))


def test_masked_out_pixels_are_never_drawn_for_training(tmp_path):
    """nerfstudio's mask_path: a pixel whose mask is 0 does not count in the loss, so the trainer never samples it."""
    folder = write_sphere_dataset(tmp_path / "s", n_views=2, size=8)
    ds = load_dataset(folder)
    masks = np.zeros((2, 8, 8), bool)
    masks[:, 2:5, 3:6] = True
    ds.images[~masks] = [1.0, 0.0, 0.0, 1.0]  # what must never be seen: pure red
    ds.images[masks] = [0.0, 1.0, 0.0, 1.0]
    ds.masks = masks
    # With the error map asked for too: a masked dataset is drawn uniformly among its valid pixels.
    trainer = Trainer(
        NerfModel(NerfConfig(aabb=ds.aabb.reshape(-1).tolist(), **SMALL)), ds, TrainOptions(steps=1, error_rays=0.5)
    )
    _, _, target, _ = trainer.sample_rays(4000)
    assert torch.equal(target, torch.tensor([0.0, 1.0, 0.0, 1.0]).expand(4000, 4))
    ds.masks = np.zeros_like(masks)
    with pytest.raises(Exception, match="masks exclude every pixel"):
        Trainer(NerfModel(NerfConfig(aabb=ds.aabb.reshape(-1).tolist(), **SMALL)), ds, TrainOptions(steps=1))
