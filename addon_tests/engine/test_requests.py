"""The engine's typed requests (engine/service/requests.py): every request round-trips through the wire,
and hostile params or arrays give one EngineError that names the request and the field."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.nerf.silhouettes import MASK_MEANINGS
from blender_nerf_deform.engine.service import requests as rq

C2W = np.eye(4)
C2W[2, 3] = 3.0
CAMERA = rq.WireCamera(32, 24, 30.0, 30.0, 16.0, 12.0, C2W, clip_start=0.1, clip_end=100.0)
REGION = {"center": [0.0, 0.0, 0.1], "size": [1.0, 1.0, 0.5], "rotation_euler": [0.0, 0.0, 0.3]}
HANDLES = rq.HandlesPose(rq.DeformMode.AFFINE, (np.eye(4), np.diag([1.0, 2.0, 1.0, 1.0])), ("Grab", "Grab.001"))
CAGE_POSE = rq.CagePose(np.arange(12, dtype=np.float64).reshape(4, 3) / 10)
MESH_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
MESH_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)

VALID = [
    rq.InfoRequest(),
    rq.LoadRequest("/runs/a/nerf.ckpt"),
    rq.LoadRequest("/runs/a/nerf.ckpt", device="cpu"),
    rq.ExtractRequest("/n.ckpt", 10.0, 64, 0.001),
    rq.ExtractRequest("/n.ckpt", 10.0, 64, 0.001, regions=(REGION, REGION), pick=(0.1, 0.2, 0.3)),
    rq.CageRequest(MESH_V, MESH_F),
    rq.CageRequest(
        MESH_V,
        MESH_F,
        cut=np.array([1, 0, 0, 0], dtype=np.uint8),
        part=np.array([0, 0, 1, 1], dtype=np.int32),
        refine=np.array([0, 1, 1, 0], dtype=np.uint8),
        checkpoint="/n.ckpt",
        threshold=10.0,
        margin=0.05,
        edge_length=0.1,
        target_tets=500,
        pin_cut=False,
        refine_edge=0.02,
    ),
    rq.CageRequest(MESH_V, MESH_F, refine_edge=0.1, refine_box=np.array([[0.0, 0, 0], [1, 1, 1]])),
    rq.TrainRequest("/data", "/run"),
    rq.TrainRequest(
        "/data",
        "/run",
        steps=100,
        max_seconds=60.0,
        device="cpu",
        downscale=2,
        resume=True,
        overwrite=True,
        scene=rq.SceneModel.UNBOUNDED,
        masks=rq.MaskMeaning.OBJECT,
    ),
    rq.TrainingPreviewRequest("/run/nerf.ckpt", CAMERA),
    rq.TrainingPreviewRequest("/run/nerf.ckpt", None, (40, 30)),
    rq.PrepareRequest("/photos", "/dataset"),
    rq.PrepareRequest("/photos", "/dataset", rq.Matcher.SEQUENTIAL, 800, 3),
    rq.FirstSurfaceRequest("/n.ckpt", (0.0, 0.0, 3.0), (0.0, 0.0, -1.0)),
    rq.FirstSurfaceRequest("/n.ckpt", (0.0, 0.0, 3.0), (0.0, 0.0, -1.0), threshold=5.0, device="cpu"),
    rq.SolveRequest(HANDLES),
    rq.SolveRequest(HANDLES, rq.SolveAnswer.SURFACE),
    rq.RenderRequest("/n.ckpt", CAMERA),
    rq.RenderRequest("/n.ckpt", CAMERA, CAGE_POSE, substeps=2),
    rq.RenderRequest("/n.ckpt", CAMERA, HANDLES, substeps=1),
    rq.WarmRequest(("/a.ckpt", "/b.ckpt")),
    rq.BakeVolumeRequest("/n.ckpt"),
    rq.BakeVolumeRequest("/n.ckpt", CAGE_POSE, rq.Extent.CAGE, 64, 2),
    rq.BakeVolumeRequest("/n.ckpt", HANDLES, REGION, 32, 1, device="cpu"),
]


@pytest.mark.parametrize("request_", VALID, ids=lambda r: type(r).__name__)
def test_every_request_round_trips_through_the_wire(request_):
    params, arrays = request_.to_wire()
    back = type(request_).from_wire(params, arrays)
    assert back == request_
    assert back.to_wire()[0] == params
    assert rq.REQUESTS[request_.op] is type(request_)


def test_every_op_of_the_worker_has_a_request_type():
    from blender_nerf_deform.engine.service import ops  # noqa: F401  (registers the handlers)
    from blender_nerf_deform.engine.service.registry import HANDLERS

    assert set(HANDLERS) == set(rq.REQUESTS) == set(rq.Op)
    assert tuple(rq.MaskMeaning) == MASK_MEANINGS


def test_the_wire_of_a_frame_is_what_it_has_always_been():
    """A render request as the add-on sent it before these types: the same params, key for key."""
    c2w = C2W.tolist()
    camera = {"width": 32, "height": 24, "fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0, "camera_to_world": c2w}
    camera.update(clip_start=0.1, clip_end=100.0)
    handles = {"kind": "handles", "mode": "AFFINE", "transforms": [t.tolist() for t in HANDLES.transforms]}
    handles["handle_names"] = ["Grab", "Grab.001"]
    for pose, arrays in (({"kind": "rest"}, {}), (handles, {}), ({"kind": "cage"}, {"deformed_vertices": MESH_V})):
        before = {"checkpoint": "/n.ckpt", "pose": pose, "substeps": 2, "camera": camera}
        params, out = rq.RenderRequest.from_wire(before, arrays).to_wire()
        assert params == before and list(params) == list(before) and list(params["camera"]) == list(camera)
        assert out.keys() == arrays.keys() and all(np.array_equal(out[k], arrays[k]) for k in arrays)
    solve = {"mode": "ARAP", "transforms": [np.eye(4).tolist()], "handle_names": ["H"], "answer": "surface"}
    assert rq.SolveRequest.from_wire(solve, {}).to_wire()[0] == solve
    train = {"data": "/d", "out": "/r", "device": "auto", "downscale": 1, "resume": False, "masks": "auto"}
    train.update(max_seconds=60.0, steps=100)
    assert rq.TrainRequest.from_wire(train).to_wire()[0] == train


def _refused(cls, params, arrays, field, *more):
    with pytest.raises(EngineError) as error:
        cls.from_wire(params, arrays)
    message = str(error.value)
    assert message.startswith(f"{cls.op} request: ") and f" {field}" in message, message
    for text in more:
        assert text in message, message
    return message


def _render(**changes):
    params, arrays = rq.RenderRequest("/n.ckpt", CAMERA, CAGE_POSE, substeps=2).to_wire()
    params = {**params, **{k: v for k, v in changes.items() if k != "arrays"}}
    return params, changes.get("arrays", arrays)


def test_hostile_render_requests_name_the_field():
    R = rq.RenderRequest
    _refused(R, *_render(pose={"kind": "bent"}), "pose.kind", "rest, cage or handles")
    _refused(R, *_render(pose=[1]), "pose:")
    _refused(R, *_render(arrays={}), "pose.deformed_vertices", "missing")
    bad = np.zeros((4, 2), dtype=np.int64)
    _refused(R, *_render(arrays={"deformed_vertices": bad}), "pose.deformed_vertices", "float", "int64 (4, 2)")
    wrong_dtype = np.zeros((4, 3), dtype=np.int32)
    _refused(R, *_render(arrays={"deformed_vertices": wrong_dtype}), "pose.deformed_vertices", "int32")
    nan = CAGE_POSE.deformed_vertices.copy()
    nan[2, 1] = np.nan
    _refused(R, *_render(arrays={"deformed_vertices": nan}), "pose.deformed_vertices", "row 2")
    far = CAGE_POSE.deformed_vertices.copy()
    far[1] = 1e10
    _refused(R, *_render(arrays={"deformed_vertices": far}), "pose.deformed_vertices", "vertex 1")
    params, arrays = _render()
    _refused(R, {k: v for k, v in params.items() if k != "checkpoint"}, arrays, "checkpoint", "missing")
    _refused(R, {**params, "checkpoint": 3}, arrays, "checkpoint", "got 3")
    _refused(R, {k: v for k, v in params.items() if k != "camera"}, arrays, "camera", "missing")
    for key, value in (("fx", "wide"), ("fy", 0.0), ("cx", float("inf")), ("width", 0), ("height", 2.5)):
        _refused(R, {**params, "camera": {**params["camera"], key: value}}, arrays, f"camera.{key}")
    camera = {k: v for k, v in params["camera"].items() if k != "height"}
    _refused(R, {**params, "camera": camera}, arrays, "camera.height", "missing")
    _refused(R, {**params, "camera": {**params["camera"], "camera_to_world": [[1, 0], [0, 1]]}}, arrays, "camera.cam")
    nan_c2w = np.eye(4)
    nan_c2w[0, 3] = np.nan
    _refused(R, {**params, "camera": {**params["camera"], "camera_to_world": nan_c2w.tolist()}}, arrays, "camera.c")
    for substeps in (0, 17, 1.5, "2", True, None):
        _refused(R, {**params, "substeps": substeps}, arrays, "substeps", "1 to 16")
    handles, _ = rq.RenderRequest("/n.ckpt", CAMERA, HANDLES).to_wire()
    _refused(R, {**handles, "pose": {**handles["pose"], "mode": "BEND"}}, {}, "pose.mode", "ARAP or AFFINE")
    _refused(R, {**handles, "pose": {**handles["pose"], "transforms": "up"}}, {}, "pose.transforms")
    bad_transforms = [np.eye(4).tolist(), [[1, 2, 3]]]
    _refused(R, {**handles, "pose": {**handles["pose"], "transforms": bad_transforms}}, {}, "pose.transforms[1]")
    _refused(R, {**handles, "pose": {**handles["pose"], "handle_names": [1]}}, {}, "pose.handle_names")
    with pytest.raises(EngineError, match="render request: params: expected a JSON object"):
        R.from_wire([], {})


def test_a_camera_reads_on_its_own():
    assert rq.WireCamera.from_wire(CAMERA.to_wire()) == CAMERA
    assert rq.WireCamera.from_wire(CAMERA.to_wire()).camera().c2w.tolist() == C2W.tolist()
    with pytest.raises(EngineError, match=r"^camera: camera.fy: expected a finite non-zero number, got 0"):
        rq.WireCamera.from_wire({**CAMERA.to_wire(), "fy": 0})


def test_a_cage_pose_must_have_the_rest_cage_shape():
    CAGE_POSE.check_cage(np.zeros((4, 3)))
    with pytest.raises(EngineError, match=r"render request: pose.deformed_vertices: 4 vertices for a cage of 5"):
        CAGE_POSE.check_cage(np.zeros((5, 3)))


def test_hostile_cage_requests_name_the_field():
    C = rq.CageRequest
    params, arrays = C(MESH_V, MESH_F, refine=np.ones(4, dtype=np.uint8)).to_wire()
    _refused(C, params, {"faces": MESH_F}, "vertices", "missing")
    _refused(C, params, {**arrays, "vertices": MESH_V[:, :2]}, "vertices", "(N, 3)")
    _refused(C, params, {**arrays, "vertices": MESH_V.astype(np.int64)}, "vertices", "int64")
    nan = MESH_V.copy()
    nan[3, 0] = np.inf
    _refused(C, params, {**arrays, "vertices": nan}, "vertices", "row 3 is not finite")
    _refused(C, params, {**arrays, "faces": MESH_F.astype(np.float32)}, "faces", "float32")
    _refused(C, params, {**arrays, "faces": MESH_F + 1}, "faces", "outside 0..3")
    _refused(C, params, {**arrays, "cut": np.ones(3, dtype=np.uint8)}, "cut", "3 cut flags for a mesh of 4")
    _refused(C, params, {**arrays, "part": np.zeros(4, dtype=np.float64)}, "part", "integer")
    _refused(C, params, {**arrays, "refine": np.ones(5, dtype=bool)}, "refine", "5 refinement flags")
    for value in (float("nan"), -0.1, "0.1", True):
        _refused(C, {**params, "refine_edge": value}, arrays, "refine_edge", "positive length")
    assert C.from_wire({**params, "refine_edge": 0}, arrays).refine_edge is None  # 0: the default edge
    for name, value in (("margin", -1.0), ("edge_length", 0), ("target_tets", 0), ("threshold", float("nan"))):
        _refused(C, {**params, name: value}, arrays, name)
    _refused(C, {**params, "pin_cut": "no"}, arrays, "pin_cut", "true or false")
    _refused(C, {**params, "checkpoint": ""}, arrays, "checkpoint")
    plain = {k: v for k, v in arrays.items() if k != "refine"}
    _refused(C, {**params, "refine_box": [0, 0, 0, 1, 1, 1]}, plain, "refine_box", "needs refine_edge")
    _refused(C, {**params, "refine_box": [0, 1], "refine_edge": 0.1}, plain, "refine_box")


def test_hostile_requests_of_every_other_op_name_the_field():
    _refused(rq.LoadRequest, {}, {}, "path", "missing")
    _refused(rq.LoadRequest, {"path": "/n.ckpt", "device": 3}, {}, "device")
    E = rq.ExtractRequest
    _refused(E, {"checkpoint": "/n.ckpt", "regions": {"center": 1}}, {}, "regions", "a list of edit regions")
    _refused(E, {"checkpoint": "/n.ckpt", "regions": [REGION, {"center": [0, 0, 0]}]}, {}, "regions[1]", "`size`")
    _refused(E, {"checkpoint": "/n.ckpt", "pick": [0, 1]}, {}, "pick", "three finite numbers")
    _refused(E, {"checkpoint": "/n.ckpt", "pick": [0, 1, float("nan")]}, {}, "pick")
    _refused(E, {"checkpoint": "/n.ckpt", "resolution": "high"}, {}, "resolution")
    T = rq.TrainRequest
    _refused(T, {"out": "/r"}, {}, "data", "missing")
    _refused(T, {"data": "/d", "out": ""}, {}, "out")
    for name, value in (("downscale", 0), ("downscale", "2"), ("steps", 1.5), ("max_seconds", -1), ("resume", 1)):
        _refused(T, {"data": "/d", "out": "/r", name: value}, {}, name)
    _refused(T, {"data": "/d", "out": "/r", "masks": "all"}, {}, "masks", "auto, object, ignore")
    _refused(T, {"data": "/d", "out": "/r", "scene": "room"}, {}, "scene", "auto, bounded, unbounded")
    P = rq.TrainingPreviewRequest
    _refused(P, {"camera": None, "size": [8, 8]}, {}, "checkpoint", "missing")
    _refused(P, {"checkpoint": "/c"}, {}, "camera", "missing")
    _refused(P, {"checkpoint": "/c", "camera": "front"}, {}, "camera", "a camera")
    _refused(P, {"checkpoint": "/c", "camera": None, "size": [8]}, {}, "size", "[width, height]")
    _refused(P, {"checkpoint": "/c", "camera": None, "size": [5000, 8]}, {}, "size", "at most 1024x1024")
    _refused(P, {"checkpoint": "/c", "camera": {**CAMERA.to_wire(), "fx": float("nan")}}, {}, "camera.fx")
    assert P.run_of({"checkpoint": "/c"}) == "/c" and P.run_of({"checkpoint": 3}) is None and P.run_of([]) is None
    Q = rq.PrepareRequest
    _refused(Q, {"out": "/d"}, {}, "images", "missing")
    _refused(Q, {"images": "/p", "out": "/d", "matcher": "fast"}, {}, "matcher", "exhaustive, sequential")
    _refused(Q, {"images": "/p", "out": "/d", "max_size": "big"}, {}, "max_size", "an integer")
    _refused(Q, {"images": "/p", "out": "/d", "seed": True}, {}, "seed")
    F = rq.FirstSurfaceRequest
    _refused(F, {"checkpoint": "/c", "direction": [0, 0, 1]}, {}, "origin", "three finite numbers")
    _refused(F, {"checkpoint": "/c", "origin": [0, 0, 1], "direction": [0, float("inf"), 1]}, {}, "direction")
    _refused(F, {"checkpoint": "/c", "origin": [0, 0, 1], "direction": [0, 0, 1], "threshold": "x"}, {}, "threshold")
    S = rq.SolveRequest
    _refused(S, {"kind": "cage"}, {}, "kind", "handles")
    _refused(S, {"mode": 3}, {}, "mode", "ARAP or AFFINE")
    _refused(S, {"transforms": [np.eye(3).tolist()]}, {}, "transforms[0]", "4x4")
    _refused(S, {"answer": "mesh"}, {}, "answer", "surface")
    assert S.from_wire({"kind": "handles", "mode": "ARAP"}).pose == rq.HandlesPose()
    W = rq.WarmRequest
    for bad in ("x", [1], None, {"a": 1}):
        _refused(W, {"checkpoints": bad}, {}, "checkpoints", "checkpoint paths")
    B = rq.BakeVolumeRequest
    _refused(B, {"pose": {"kind": "rest"}}, {}, "checkpoint", "missing")
    _refused(B, {"checkpoint": "/c", "extent": "world"}, {}, "extent", "nerf, cage")
    _refused(B, {"checkpoint": "/c", "extent": "cage"}, {}, "extent", "cage needs")
    _refused(B, {"checkpoint": "/c", "extent": {"center": [0, 0, 0]}}, {}, "extent", "`size`")
    _refused(B, {"checkpoint": "/c", "resolution": 0}, {}, "resolution", "whole number")
    _refused(B, {"checkpoint": "/c", "supersample": 0}, {}, "supersample")
    _refused(B, {"checkpoint": "/c", "pose": {"kind": "cage"}}, {}, "pose.deformed_vertices", "missing")


def test_requests_import_without_torch():
    """The add-on imports this module in Blender's Python, which has numpy and no torch."""
    code = "import sys, blender_nerf_deform.engine.service.requests; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
