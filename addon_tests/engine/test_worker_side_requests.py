"""The worker answers side requests while it trains: a training_preview of the running run is
rendered between training steps (the reader hands it to the train job instead of queueing it
behind it), without disturbing the training; other previews wait and render the checkpoint file.
The new ops (training_preview, prepare) refuse hostile params with a clear input error. A real
worker process on this Python, spoken to through the wire format."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from fixtures import REPO
from fixtures.sfm_scene import write_corner_photos
from fixtures.sphere_data import write_sphere_dataset

from blender_nerf_deform.engine.service.protocol import read_message, write_message


class Conversation:
    """A worker process and the messages it sent, read in order."""

    def __init__(self):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "blender_nerf_deform.engine.service.worker"],
            cwd=REPO,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )
        hello, _ = read_message(self.proc.stdout)
        assert hello["type"] == "hello" and "training_preview" in hello["ops"] and "prepare" in hello["ops"]
        self.log: list[tuple[dict, dict]] = []

    def send(self, header: dict, arrays: dict | None = None) -> None:
        write_message(self.proc.stdin, header, arrays)

    def request(self, request_id: int, op: str, params: dict, arrays: dict | None = None) -> None:
        self.send({"type": "request", "id": request_id, "op": op, "params": params}, arrays)

    def next(self) -> tuple[dict, dict]:
        message = read_message(self.proc.stdout)
        assert message is not None, "the worker ended"
        self.log.append(message)
        return message

    def until(self, request_id: int, kinds=("result", "error")) -> tuple[dict, dict]:
        """Read until a message of `kinds` for `request_id` comes; what came before stays in `log`."""
        while True:
            header, arrays = self.next()
            if header.get("id") == request_id and header["type"] in kinds:
                return header, arrays

    def close(self) -> None:
        try:
            self.send({"type": "shutdown"})
            self.proc.stdin.close()
            self.proc.wait(timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def worker():
    conversation = Conversation()
    yield conversation
    conversation.close()


def _answered(log, request_id) -> int:
    """Position in the log of the request's answer."""
    return next(k for k, (h, _) in enumerate(log) if h.get("id") == request_id and h["type"] in ("result", "error"))


@pytest.mark.slow
def test_a_preview_is_answered_while_the_training_runs_and_leaves_it_undisturbed(worker, tmp_path):
    data = write_sphere_dataset(tmp_path / "data", n_views=12, size=24)
    run, quiet = tmp_path / "run", tmp_path / "quiet"
    ckpt = str(run / "nerf.ckpt")
    steps = 150
    worker.request(1, "train", {"data": str(data), "out": str(run), "steps": steps, "device": "cpu"})
    worker.until(1, kinds=("progress",))  # it trains
    camera = {"camera": None, "size": [40, 30]}
    worker.request(2, "training_preview", {"checkpoint": ckpt, **camera})
    worker.request(3, "training_preview", {"checkpoint": ckpt, "camera": "the front"})  # bad: answered too
    worker.request(4, "training_preview", {"checkpoint": str(tmp_path / "other" / "nerf.ckpt"), **camera})  # not ours
    worker.request(5, "training_preview", {**camera})  # no checkpoint: not handed to the training
    preview, arrays = worker.until(2)
    assert preview["type"] == "result", preview
    result = preview["result"]
    assert result["source"] == "training" and 0 < result["step"] < steps
    rgba = arrays["rgba"]
    assert rgba.shape == (30, 40, 4) and np.isfinite(rgba).all()
    assert rgba[..., 3].std() > 0.05 and rgba[..., :3].std() > 0.02  # the sphere's disc, not a constant image
    bad, _ = worker.until(3)
    assert bad["type"] == "error" and bad["kind"] == "input" and "camera: expected a camera" in bad["message"]
    trained, _ = worker.until(1)
    assert trained["type"] == "result" and trained["result"]["steps"] == steps, trained
    # Both previews of the running training came back before it ended; the others waited for it.
    assert _answered(worker.log, 2) < _answered(worker.log, 1) and _answered(worker.log, 3) < _answered(worker.log, 1)
    other, _ = worker.until(4)
    assert other["type"] == "error" and other["kind"] == "input" and "does not exist yet" in other["message"]
    missing, _ = worker.until(5)
    assert missing["kind"] == "input" and "checkpoint: missing" in missing["message"]
    assert _answered(worker.log, 1) < _answered(worker.log, 4)

    # After the training: the preview renders the checkpoint file, from the same camera.
    worker.request(6, "training_preview", {"checkpoint": ckpt, **camera})
    done, done_arrays = worker.until(6)
    assert done["type"] == "result" and done["result"]["source"] == "checkpoint"
    assert done_arrays["rgba"].shape == (30, 40, 4) and done_arrays["rgba"][..., 3].std() > 0.05

    # The previews did not disturb the training: the same steps without them give the same weights.
    worker.request(7, "train", {"data": str(data), "out": str(quiet), "steps": steps, "device": "cpu"})
    assert worker.until(7)[0]["type"] == "result"
    a = torch.load(ckpt, map_location="cpu", weights_only=True)
    b = torch.load(quiet / "nerf.ckpt", map_location="cpu", weights_only=True)
    assert a["state"].keys() == b["state"].keys() and a["trainer"]["step"] == b["trainer"]["step"] == steps
    for name in a["state"]:
        assert torch.equal(a["state"][name], b["state"][name]), name
    assert torch.equal(a["occupancy"]["density"], b["occupancy"]["density"])


def test_hostile_preview_and_prepare_params_are_input_errors(worker, tmp_path):
    photos = tmp_path / "photos"
    cases = [
        ("training_preview", {}, "training_preview request: checkpoint: missing"),
        ("training_preview", {"checkpoint": 7, "camera": None}, "checkpoint: expected the path of"),
        ("training_preview", {"checkpoint": str(tmp_path / "nerf.ckpt")}, "camera: missing"),
        (
            "training_preview",
            {"checkpoint": str(tmp_path / "nerf.ckpt"), "camera": None, "size": [8, 8]},
            "does not exist yet",
        ),
        ("prepare", {}, "prepare request: images: missing"),
        ("prepare", {"images": ["a"], "out": "x"}, "images: expected a folder"),
        ("prepare", {"images": str(photos), "out": None}, "out: expected a dataset folder"),
        ("prepare", {"images": str(photos), "out": str(tmp_path / "d"), "matcher": 3}, "matcher: expected one of"),
        (
            "prepare",
            {"images": str(photos), "out": str(tmp_path / "d"), "max_size": "big"},
            "max_size: expected an integer",
        ),
        ("prepare", {"images": str(photos), "out": str(tmp_path / "d"), "seed": True}, "seed: expected an integer"),
        ("prepare", {"images": str(photos), "out": str(tmp_path / "d")}, "no such folder"),
        (
            "train",
            {"data": str(photos), "out": str(tmp_path / "r"), "downscale": "2"},
            "downscale: expected a whole number",
        ),
        (
            "train",
            {"data": str(photos), "out": str(tmp_path / "r"), "downscale": 0},
            "downscale: expected a whole number",
        ),
    ]
    for k, (op, params, message) in enumerate(cases):
        worker.request(k, op, params)
        header, _ = worker.until(k)
        assert header["type"] == "error" and header["kind"] == "input", (op, params, header)
        assert message in header["message"] and "Traceback" not in header["message"], (op, params, header["message"])


def test_hostile_cage_refinement_is_an_input_error_before_any_tetrahedralizing(worker):
    """Build Cage's Refine Selected arrives as flags and an edge length: wrong ones are named at once."""
    from blender_nerf_deform.engine.geometry.barycentric import boundary_faces
    from blender_nerf_deform.engine.geometry.cage import box_cage

    v, t = box_cage((2, 2, 2))
    mesh = {"vertices": v.astype(np.float64), "faces": boundary_faces(t).astype(np.int64)}
    flags = np.ones(len(v), dtype=np.uint8)
    cases = [
        ({}, {"refine": flags[:-1]}, "refinement flags for a mesh of"),
        ({"refine_edge": float("nan")}, {"refine": flags}, "refine_edge: expected a positive length"),
        ({"refine_edge": -0.1}, {"refine": flags}, "refine_edge: expected a positive length"),
        ({"refine_edge": "0.1"}, {"refine": flags}, "refine_edge: expected a positive length"),
        ({"refine_edge": True}, {"refine": flags}, "refine_edge: expected a positive length"),
    ]
    for k, (params, extra, message) in enumerate(cases):
        worker.request(k, "cage", params, {**mesh, **extra})
        header, _ = worker.until(k)
        assert header["type"] == "error" and header["kind"] == "input", (params, header)
        assert message in header["message"] and "Traceback" not in header["message"], (params, header["message"])
        progress = [h for h, _ in worker.log if h.get("id") == k and h["type"] == "progress"]
        assert not progress, progress  # refused before tetrahedralizing


def test_hostile_preview_cameras_of_a_checkpoint_are_input_errors(worker, sphere_nerf):
    ckpt = str(sphere_nerf[0])
    pose = np.eye(4)
    pose[2, 3] = 3.0
    good = {"camera_to_world": pose.tolist(), "fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0, "width": 32, "height": 24}
    cases = [
        ({"camera": None}, "size: expected [width, height]"),
        ({"camera": None, "size": [32]}, "size: expected [width, height]"),
        ({"camera": None, "size": ["32", 24]}, "size: expected [width, height]"),
        ({"camera": None, "size": [5000, 24]}, "at most 1024x1024"),
        ({"camera": {**good, "fx": "wide"}}, "camera.fx: expected a finite non-zero number"),
        ({"camera": {k: v for k, v in good.items() if k != "width"}}, "camera.width: missing"),
        ({"camera": {**good, "fx": float("nan")}}, "camera.fx: expected a finite non-zero number"),
        ({"camera": {**good, "height": 0}}, "camera.height: expected a whole number of pixels >= 1"),
        ({"camera": {**good, "height": 2000}}, "at most 1024x1024"),
    ]
    for k, (params, message) in enumerate(cases):
        worker.request(k, "training_preview", {"checkpoint": ckpt, **params})
        header, _ = worker.until(k)
        assert header["type"] == "error" and header["kind"] == "input", (params, header)
        assert message in header["message"], (params, header["message"])
    worker.request(99, "training_preview", {"checkpoint": ckpt, "camera": good})
    header, arrays = worker.until(99)
    assert header["type"] == "result" and arrays["rgba"].shape == (24, 32, 4) and arrays["rgba"][..., 3].max() > 0.5


def test_a_render_request_with_bad_substeps_is_an_input_error_and_good_ones_render(worker, sphere_nerf):
    """The `render` op's substeps (the add-on's Render Substeps, sent as JSON): anything but an integer
    from 1 to MAX_SUBSTEPS is one input error, before the NeRF is loaded; 1 and FINAL_SUBSTEPS render."""
    from blender_nerf_deform.engine.nerf.substeps import FINAL_SUBSTEPS, MAX_SUBSTEPS

    pose = np.eye(4)
    pose[2, 3] = 3.0
    params = {
        "checkpoint": str(sphere_nerf[0]),
        "pose": {"kind": "rest"},
        "camera": {
            "camera_to_world": pose.tolist(),
            "fx": 30.0,
            "fy": 30.0,
            "cx": 16.0,
            "cy": 12.0,
            "width": 32,
            "height": 24,
        },
    }
    for k, bad in enumerate([0, MAX_SUBSTEPS + 1, 1.5, "2", True, None, float("nan")]):
        worker.request(k, "render", {**params, "substeps": bad})
        header, _ = worker.until(k)
        assert header["type"] == "error" and header["kind"] == "input", (bad, header)
        assert "substeps" in header["message"] and "1 to 16" in header["message"], (bad, header["message"])
    images = {}
    for k, substeps in enumerate((1, FINAL_SUBSTEPS), start=50):
        worker.request(k, "render", {**params, "substeps": substeps})
        header, arrays = worker.until(k)
        assert header["type"] == "result", header
        images[substeps] = arrays["rgba"]
    assert images[1].shape == (24, 32, 4) and images[1][..., 3].max() > 0.5
    assert not np.array_equal(images[1], images[FINAL_SUBSTEPS])  # the finer march is another quadrature


@pytest.mark.slow
def test_prepare_op_reports_its_stages_and_a_cancel_leaves_nothing(worker, tmp_path):
    write_corner_photos(tmp_path / "photos", n_views=8, width=160, height=120, focal=130.0)
    out = tmp_path / "run" / "dataset"
    worker.request(1, "prepare", {"images": str(tmp_path / "photos"), "out": str(out)})
    done, _ = worker.until(1)
    assert done["type"] == "result", done
    assert done["result"]["registered"] == 8 and (out / "transforms.json").is_file()
    messages = [h["message"] for h, _ in worker.log if h.get("id") == 1 and h["type"] == "progress"]
    fractions = [h["fraction"] for h, _ in worker.log if h.get("id") == 1 and h["type"] == "progress"]
    assert any("features" in m for m in messages) and any("matching" in m for m in messages)
    assert any("photos placed" in m for m in messages) and fractions == sorted(fractions)

    # Cancelled while pycolmap works: an error of kind cancelled, no dataset, no work folder, no run folder.
    out2 = tmp_path / "run2" / "dataset"
    worker.request(2, "prepare", {"images": str(tmp_path / "photos"), "out": str(out2)})
    worker.until(2, kinds=("progress",))
    time.sleep(0.3)
    worker.send({"type": "cancel", "id": 2})
    started = time.perf_counter()
    cancelled, _ = worker.until(2)
    assert cancelled["type"] == "error" and cancelled["kind"] == "cancelled", cancelled
    assert time.perf_counter() - started < 3.0
    assert not (tmp_path / "run2").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos", "run"]


def test_warm_loads_each_checkpoint_and_renders_a_view_of_it_and_refuses_bad_params(worker, sphere_nerf, tmp_path):
    """`warm` (what Blender sends when a file with NeRFs opens): each checkpoint loaded and a small view
    of its box rendered, which meets the NeRF (colour samples > 0: every frame kernel ran); then a frame
    of it renders. Anything but a list of paths, or a path that is no checkpoint, is one input error."""
    broken = tmp_path / "broken.ckpt"
    broken.write_bytes(b"not a checkpoint")
    for k, bad in enumerate(["x", [1], None, {"a": 1}, [str(tmp_path / "missing.ckpt")], [str(broken)]]):
        worker.request(k, "warm", {"checkpoints": bad})
        header, _ = worker.until(k)
        assert header["type"] == "error" and header["kind"] == "input", (bad, header)
        assert "checkpoint" in header["message"], (bad, header["message"])
    worker.request(20, "warm", {"checkpoints": [str(sphere_nerf[0])]})
    header, _ = worker.until(20)
    assert header["type"] == "result", header
    assert len(header["result"]["color_samples_per_ray"]) == 1 and header["result"]["color_samples_per_ray"][0] > 0
    assert any(
        h.get("id") == 20 and h["type"] == "progress" and "loaded" in h.get("message", "") for h, _ in worker.log
    )
    pose = np.eye(4)
    pose[2, 3] = 3.0
    worker.request(
        21,
        "render",
        {
            "checkpoint": str(sphere_nerf[0]),
            "pose": {"kind": "rest"},
            "camera": {
                "camera_to_world": pose.tolist(),
                "fx": 30.0,
                "fy": 30.0,
                "cx": 16.0,
                "cy": 12.0,
                "width": 32,
                "height": 24,
            },
        },
    )
    header, arrays = worker.until(21)
    assert header["type"] == "result" and arrays["rgba"][..., 3].max() > 0.5
