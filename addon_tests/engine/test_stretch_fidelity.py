"""Stretch fidelity of ray bending (issue 18): cage refinement where a pose stretches, the density scale
(rest-space length of a step along the ray) and the finer step where a pose compresses, and a CI-sized
version of the ground-truth benchmark's stretch map (tools/bench/bending_groundtruth.py: a Cycles-rendered
bar with a UV checker, a band of it stretched to 2.7x its height)."""

import json
import sys

import numpy as np
import pytest
from fixtures import REPO

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.geometry.barycentric import boundary_faces, signed_volumes
from blender_nerf_deform.engine.geometry.cage import box_cage
from blender_nerf_deform.engine.geometry.cage_refine import extend_vertex_labels, refine_around, refine_cage

sys.path.insert(0, str(REPO / "tools" / "bench"))
import bending_groundtruth as bench  # noqa: E402


def _area(V, F):
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()


def _longest_edges(V, T):
    e = T[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]]
    return np.linalg.norm(V[e[..., 0]] - V[e[..., 1]], axis=2).max(axis=1)


def test_refining_a_cage_in_a_box_is_conforming_and_keeps_its_shape():
    V, T = box_cage((3, 3, 6), lo=(-0.5, -0.5, -1.0), hi=(0.5, 0.5, 1.0))
    box = np.array([[-1.0, -1.0, -0.2], [1.0, 1.0, 0.2]])
    V2, T2 = refine_cage(V, T, 0.12, box)
    assert np.array_equal(V2[: len(V)], V)  # the original vertices keep their indices
    vol = signed_volumes(V2, T2)
    assert vol.min() > 0 and np.isclose(vol.sum(), signed_volumes(V, T).sum())
    # Conforming: no face is shared by more than two tets, and the boundary is the same surface.
    faces = np.sort(T2[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    assert np.unique(faces, axis=0, return_counts=True)[1].max() == 2
    assert np.isclose(_area(V2, boundary_faces(T2)), _area(V, boundary_faces(T)))
    centroid = V2[T2].mean(axis=1)
    inside = ((centroid >= box[0]) & (centroid <= box[1])).all(axis=1)
    assert _longest_edges(V2, T2)[inside].max() <= 0.12
    far = np.abs(centroid[:, 2]) > 0.75  # away from the box the cage stays as it was
    assert _longest_edges(V2, T2)[far].min() > 0.3
    # Everywhere, without a box.
    V3, T3 = refine_cage(V, T, 0.3)
    assert _longest_edges(V3, T3).max() <= 0.3 and signed_volumes(V3, T3).min() > 0


@pytest.mark.parametrize(
    "bad", [dict(max_edge=0.0), dict(max_edge=float("nan")), dict(box=[[0, 0, 1], [1, 1, 0]]), dict(box=[[0, 0, 0]])]
)
def test_refining_with_bad_input_is_an_engine_error(bad):
    V, T = box_cage((2, 2, 2))
    kw = dict(max_edge=0.2, box=None) | bad
    with pytest.raises(EngineError, match="refinement"):
        refine_cage(V, T, kw["max_edge"], kw["box"])


def test_refining_around_a_selection_of_a_two_part_cage_labels_every_new_vertex_with_its_part():
    """Build Cage's Refine Selected on a cage of two objects (edit regions): the box is the selection's
    widened by margin and edge; new vertices get their own object's part."""
    v0, t0 = box_cage((3, 3, 3), lo=(0, 0, 0), hi=(1, 1, 1))
    v1, t1 = box_cage((3, 3, 3), lo=(2, 0, 0), hi=(3, 1, 1))
    V, T = np.concatenate([v0, v1]), np.concatenate([t0, t1 + len(v0)])
    part = np.repeat([0, 1], [len(v0), len(v1)])
    selection = np.array([[0.9, 0.5, 0.5], [2.1, 0.5, 0.5]])  # a point of each object, near the gap
    V2, T2, edge, box = refine_around(V, T, selection, margin=0.05)
    assert edge == pytest.approx(
        0.5 * np.median(np.linalg.norm(V[T[:, [0, 0, 0, 1, 1, 2]]] - V[T[:, [1, 2, 3, 2, 3, 3]]], axis=-1))
    )
    assert np.allclose(
        box,
        [
            [0.9 - 0.05 - edge, 0.5 - 0.05 - edge, 0.5 - 0.05 - edge],
            [2.1 + 0.05 + edge, 0.5 + 0.05 + edge, 0.5 + 0.05 + edge],
        ],
    )
    assert len(T2) > len(T) and (signed_volumes(V2, T2) > 0).all()
    labels = extend_vertex_labels(part, T2, len(V2))
    assert (labels[: len(part)] == part).all() and (labels >= 0).all()
    assert (labels[T2] == labels[T2][:, :1]).all()  # no tet joins two objects
    assert ((V2[len(V) :, 0] < 1.5) == (labels[len(V) :] == 0)).all()
    with pytest.raises(EngineError, match="no vertices are selected"):
        refine_around(V, T, np.zeros((0, 3)), margin=0.05)


def test_the_cage_command_refuses_a_refinement_box_without_an_edge_length(tmp_path):
    import subprocess

    for extra, message in (
        (["--refine-box", 0, 0, 0, 1, 1, 1], "--refine-box needs --refine-edge"),
        (["--refine-edge", -0.1], "--refine-edge must be a positive length"),
    ):
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "blender_nerf_deform.engine",
                "cage",
                "--nerf",
                tmp_path / "n.ckpt",
                "--mesh",
                tmp_path / "m.ply",
                "--out",
                tmp_path / "c.npz",
                *map(str, extra),
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
        )
        assert proc.returncode != 0 and message in proc.stderr + proc.stdout, proc.stderr
        assert not (tmp_path / "c.npz").exists()


def test_a_refined_cage_carries_the_stretch_map_close_to_exact():
    """The benchmark's stretch (a band 0.3 tall stretched 2.7x, 3.55x at its middle) on a cage with the
    engine's default-sized tets (~0.2) puts the bar's surface off its place; refining the band fixes it."""
    V, T = box_cage((4, 3, 10), lo=(-0.6, -0.5, -1.3), hi=(0.6, 0.5, 1.45))
    lo, hi = np.array(bench.BAR[0]), np.array(bench.BAR[1])
    g = np.stack(np.meshgrid(*[np.linspace(lo[i], hi[i], 9) for i in range(3)], indexing="ij"), -1).reshape(-1, 3)
    surface = g[(np.isclose(g, lo) | np.isclose(g, hi)).any(axis=1)]
    coarse = bench.cage_map_error(surface, V, T, bench.stretch_map, 44.4)
    V2, T2 = refine_cage(V, T, 0.08, np.asarray(bench.REFINE_BOX))
    fine = bench.cage_map_error(surface, V2, T2, bench.stretch_map, 44.4)
    assert coarse["max_px"] > 1.0  # measured 2.8 px at 128 px
    assert fine["max_px"] < 0.35 * coarse["max_px"] and fine["mean"] < 0.35 * coarse["mean"]


@pytest.fixture(scope="module")
def model(sphere_nerf):
    from blender_nerf_deform.engine.nerf.checkpoint import load_nerf

    return load_nerf(sphere_nerf[0], device="cpu")


def test_a_squash_scales_density_by_the_rest_length_of_the_step_and_refines_the_step(model):
    import torch

    from blender_nerf_deform.engine import backend
    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    rest, tets = box_cage((4, 4, 4), lo=(-1.5,) * 3, hi=(1.5,) * 3)
    pts = torch.tensor([[0.2, 0.1, 0.0], [-0.3, 0.2, 0.4]], dtype=torch.float32)
    along_x = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    along_y = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    for path in ("auto", "torch"):
        with backend.forced(path):
            bend = CageBend(model, rest, tets, refine_step=True)
            bend.set_deformed(rest)  # identity: every scale exactly 1, the NeRF's own step
            assert torch.equal(bend.sample_transform(pts, along_x)[3], torch.ones(2))
            assert bend.step_refine == 1.0 and "step" not in bend.render_kwargs()
            bend.set_deformed(rest * [0.5, 1.0, 1.0])  # squashed to half its width
            _, _, _, sx = bend.sample_transform(pts, along_x)
            _, _, _, sy = bend.sample_transform(pts, along_y)
            assert torch.allclose(sx, torch.full((2,), 2.0), atol=1e-5)  # a deformed step is two rest steps
            assert torch.allclose(sy, torch.ones(2), atol=1e-5)
            assert bend.step_refine == pytest.approx(2.0)
            assert bend.render_kwargs()["step"] == pytest.approx(model.config.render_step / 2)
            # A crease: one content tet squashed 10x (a bend's inside, a tet the fold-free ARAP holds
            # near flat) does not make the whole frame march 4x finer; the frame's step is the share's.
            crease = rest.copy()
            first = int(bend._content_tets[0])
            corner = tets[first, 0]
            opposite = rest[tets[first, 1:]].mean(axis=0)
            crease[corner] = opposite + 0.1 * (rest[corner] - opposite)
            bend.set_deformed(crease)
            assert bend.step_refine == 1.0 and "step" not in bend.render_kwargs()
            bend.set_deformed(rest * [0.5, 1.0, 1.0])
            bend.refine_step = False  # the default: the frame keeps the NeRF's step
            assert "step" not in bend.render_kwargs()
            bend.refine_step = True
            bend.density_correction = False  # the renderer's older contract: three outputs
            assert len(bend.sample_transform(pts, along_x)) == 3


# --------------------------------------------------------------------------- CI-sized ground truth

# The benchmark at CI size (measured figures in the test's docstring).
SMALL = [
    "--views",
    "40",
    "--test-views",
    "4",
    "--resolution",
    "96",
    "--samples",
    "8",
    "--train-steps",
    "500",
    "--maps",
    "stretch,squash",
]


@pytest.mark.slow
def test_stretching_a_band_2_7x_renders_within_the_bound_of_the_rest_pose(tmp_path):
    """The benchmark's stretch and squash maps on a small version of its scene (40 views at 96 px, 500
    training steps, 4 test views; about 140 s on 2 cores): with the band refined (`cage --refine-edge
    0.1`), the stretched checker is drawn where Cycles draws it. Measured 2026-12-02: rest 30.03 dB;
    stretch -0.69 dB refined (surface error 0.02 / 0.50 px mean / max) and -1.48 dB with the cage as
    built (0.20 / 3.18 px), squash +1.47 dB (a narrower object: fewer pixels to get wrong). The bounds
    leave ~0.4 dB for the run-to-run spread (fTetWild builds a different cage on every run): the
    refined stretch within 1.1 dB of rest, at least 0.4 dB better than without refinement. Checked to
    fail with refine_cage made a no-op (stretch -1.33 dB "refined", -1.21 dB as built)."""
    import subprocess

    def run(*extra):
        proc = subprocess.run(
            [
                sys.executable,
                str(REPO / "tools" / "bench" / "bending_groundtruth.py"),
                "--work",
                str(tmp_path),
                *SMALL,
                *extra,
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert proc.returncode in (0, 1), proc.stdout[-3000:] + proc.stderr[-3000:]
        rows = {r["pose"]: r for r in json.loads((tmp_path / "results.json").read_text())["rows"]}
        rest = rows["rest (no cage)"]["psnr"]
        return {k: rows[k]["psnr"] - rest for k in ("stretch", "squash")}, proc.stdout

    refined, out = run("--refine-edge", "0.1")
    coarse, _ = run("--reuse")
    print(out, refined, coarse)
    assert refined["stretch"] >= -STRETCH_BOUND_DB, (refined, coarse)
    assert refined["stretch"] - coarse["stretch"] >= STRETCH_GAIN_DB, (refined, coarse)
    assert refined["squash"] >= -SQUASH_BOUND_DB, (refined, coarse)


STRETCH_BOUND_DB = 1.1
STRETCH_GAIN_DB = 0.4
SQUASH_BOUND_DB = 0.5


@pytest.mark.parametrize("value", ["0", "-5", "nan", "1.5"])
def test_a_bad_train_resolution_is_one_error_line(value, tmp_path):
    """The benchmark's --train-resolution (its own process each): refused before anything is rendered."""
    import subprocess

    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "tools" / "bench" / "bending_groundtruth.py"),
            "--work",
            str(tmp_path / "work"),
            "--train-resolution",
            value,
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    errors = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert len(errors) == 1 and "--train-resolution" in errors[0], proc.stderr
    assert not (tmp_path / "work").exists()  # nothing made
