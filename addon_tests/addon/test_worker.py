"""The worker process Blender talks to: wire format, a real worker on the .venv Python, failures."""

import io
import os
import signal
import sys

import numpy as np
import pytest
from fixtures import REPO

from blender_nerf_deform.engine.service.protocol import ProtocolError, read_message, write_message


def test_protocol_round_trip_keeps_arrays_exact():
    arrays = {
        "rgba": np.random.default_rng(0).random((3, 5, 4), dtype=np.float32),
        "tets": np.arange(12, dtype=np.int64).reshape(3, 4),
        "empty": np.zeros((0, 3)),
        "transposed": np.arange(6.0).reshape(2, 3).T,  # non-contiguous input
    }
    stream = io.BytesIO()
    write_message(stream, {"type": "result", "id": 7, "result": {"frame": 3}}, arrays)
    write_message(stream, {"type": "shutdown"})
    stream.seek(0)
    header, got = read_message(stream)
    assert header == {"type": "result", "id": 7, "result": {"frame": 3}}
    for name, a in arrays.items():
        assert got[name].dtype == a.dtype and np.array_equal(got[name], a), name
    assert read_message(stream)[0] == {"type": "shutdown"}
    assert read_message(stream) is None


def test_protocol_rejects_truncated_and_foreign_streams():
    stream = io.BytesIO()
    write_message(stream, {"type": "x"}, {"a": np.ones(100)})
    data = stream.getvalue()
    with pytest.raises(ProtocolError, match="truncated"):
        read_message(io.BytesIO(data[:-10]))
    with pytest.raises(ProtocolError, match="expected"):
        read_message(io.BytesIO(b"GARBAGE!" + data))


@pytest.fixture
def worker():
    from blender_nerf_deform.addon.worker.client import WorkerClient

    client = WorkerClient(str(REPO / ".venv" / "bin" / "python"))
    yield client
    client.stop()


def test_worker_starts_and_answers(worker):
    hello = worker.ensure_started()
    assert hello["type"] == "hello" and hello["torch"].startswith("2.") and "info" in hello["ops"]
    result, arrays = worker.call("info")
    assert result["pid"] == worker._proc.pid and result["cuda"] in (True, False)
    assert arrays == {}


def test_unknown_request_is_an_input_error_and_the_worker_lives_on(worker):
    from blender_nerf_deform.addon.worker.client import WorkerError

    with pytest.raises(WorkerError, match="unknown request 'bake'") as info:
        worker.call("bake")
    assert info.value.kind == "input"
    assert worker.call("info")[0]["pid"] == worker._proc.pid


def test_async_request_is_delivered_by_drain(worker):
    got = []
    worker.submit("info", on_done=lambda result, arrays: got.append(result))
    for _ in range(200):
        if worker.drain():
            break
        import time

        time.sleep(0.05)
    assert len(got) == 1 and got[0]["python"]


def test_crashed_worker_is_restarted_by_the_next_request(worker):
    first = worker.call("info")[0]["pid"]
    os.kill(first, signal.SIGKILL)
    worker._proc.wait()
    assert not worker.running
    second = worker.call("info")[0]["pid"]
    assert second != first


def test_request_pending_when_the_worker_dies_fails_clearly(worker):
    import time

    from blender_nerf_deform.addon.worker.client import WorkerError

    pid = worker.call("info")[0]["pid"]
    os.kill(pid, signal.SIGSTOP)  # frozen: it cannot answer what we send now
    errors = []
    worker.submit("info", on_error=errors.append, on_done=lambda *a: errors.append("answered"))
    os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 30
    while not errors and time.monotonic() < deadline:
        worker.drain()
        time.sleep(0.02)
    (error,) = errors
    assert isinstance(error, WorkerError) and error.kind == "crashed"
    assert "exited with code -9" in str(error)
    assert worker.call("info")[0]["pid"] != pid  # the next request restarts it


def test_python_without_torch_gives_a_clear_setup_error():
    from blender_nerf_deform.addon.worker.client import WorkerClient, WorkerError, python_has_torch

    # The interpreter that made .venv has neither torch nor the engine's requirements.
    base = sys._base_executable if hasattr(sys, "_base_executable") else sys.executable
    if python_has_torch(base):
        pytest.skip(f"{base} has torch; no torch-less Python to test with")
    client = WorkerClient(base)
    with pytest.raises(WorkerError, match="cannot import (torch|numpy)") as info:
        client.ensure_started()
    assert info.value.kind == "setup" and base in str(info.value)
    assert not client.running


def test_missing_worker_python_names_the_path(tmp_path):
    from blender_nerf_deform.addon.worker.client import WorkerClient, WorkerError

    missing = tmp_path / "nope" / "python"
    with pytest.raises(WorkerError, match=f"{missing} does not exist"):
        WorkerClient(str(missing)).call("info")


def test_load_of_a_missing_checkpoint_names_the_path(worker, tmp_path):
    from blender_nerf_deform.addon.worker.client import WorkerError

    assert "load" in worker.ensure_started()["ops"]
    missing = tmp_path / "runs" / "nerf.ckpt"
    with pytest.raises(WorkerError, match=f"NeRF checkpoint {missing} does not exist") as info:
        worker.call("load", {"path": str(missing)})
    assert info.value.kind == "input"


@pytest.mark.slow
def test_render_cancelled_midway_stops_at_the_next_chunk_and_the_worker_lives_on(worker, sphere_nerf):
    from blender_nerf_deform.addon.worker.client import WorkerError

    ckpt, _ = sphere_nerf
    c2w = [[1, 0, 0, 0], [0, 0, -1, -3], [0, 1, 0, 0], [0, 0, 0, 1]]  # 3 units out on -y, looking at the origin

    def request(size):
        f = 0.5 * size / np.tan(0.45)
        camera = {
            "width": size,
            "height": size,
            "fx": f,
            "fy": f,
            "cx": size / 2,
            "cy": size / 2,
            "camera_to_world": c2w,
        }
        return {"checkpoint": str(ckpt), "camera": camera}

    params = request(320)  # 102400 rays: many chunks, so there is a "midway"
    progress = []
    with pytest.raises(WorkerError) as info:
        worker.call(
            "render",
            params,
            on_progress=lambda frac, msg: progress.append(frac),
            should_cancel=lambda: len(progress) > 0,
        )
    assert info.value.kind == "cancelled"
    assert progress and max(progress) < 1.0
    result, arrays = worker.call("render", request(24))  # the same worker renders the next request in full
    assert arrays["rgba"].shape == (24, 24, 4)


def _box_session(loads):
    """Shared content of a small box cage, its vertices embedded in it, one handle and a pin."""
    from blender_nerf_deform.engine.geometry.cage import box_cage
    from blender_nerf_deform.engine.geometry.embedding import embed_points
    from blender_nerf_deform.engine.service.protocol import content_key

    V, T = box_cage((3, 3, 3), (-1, -1, -1), (1, 1, 1))
    emb = embed_points(V, V, T)
    top, bottom = np.flatnonzero(V[:, 2] > 0.9), np.flatnonzero(V[:, 2] < -0.9)
    regions = {"handle_index": top, "handle_counts": np.array([len(top)]), "pin_index": bottom}

    def loader(slot, arrays):
        def load():
            loads.append(slot)
            return arrays

        return load

    cage = {"vertices": V, "tets": T}
    embedding = {"tet_ids": emb.tet_ids, "weights": emb.weights}
    shared = {
        "cage": (content_key(V, T), loader("cage", cage)),
        "embedding": (content_key(emb.tet_ids, emb.weights), loader("embedding", embedding)),
        "regions": (content_key(*regions.values()), loader("regions", regions)),
    }
    return V, top, shared


def _lift(dz):
    m = np.eye(4)
    m[2, 3] = dz
    return m.tolist()


def test_shared_content_travels_once_and_again_after_a_restart(worker):
    """The worker session: cage, embedding and regions are sent with the first request that needs
    them, named by key afterwards; a new worker process gets them again."""
    loads = []
    V, top, shared = _box_session(loads)
    pose = {"mode": "ARAP", "transforms": [_lift(0.3)], "handle_names": ["Lift"]}
    result, out = worker.call("solve", pose, shared=shared)
    assert sorted(loads) == ["cage", "embedding", "regions"] and "precompute_s" in result
    first_bytes = worker.sent[-1][1]
    # The handle pulls its region (soft, surface_arap): within a thousandth of the cage's size.
    assert np.allclose(out["deformed_vertices"][top, 2], V[top, 2] + 0.3, atol=1e-3 * np.linalg.norm(np.ptp(V, axis=0)))

    loads.clear()
    result, out2 = worker.call("solve", {**pose, "transforms": [_lift(0.5)]}, shared=shared)
    assert loads == [] and "precompute_s" not in result  # nothing re-sent, factorization reused
    assert worker.sent[-1][1] < 2000 < first_bytes
    assert np.allclose(
        out2["deformed_vertices"][top, 2], V[top, 2] + 0.5, atol=1e-3 * np.linalg.norm(np.ptp(V, axis=0))
    )
    # The preview's answer: the embedded surface itself (here: the cage's own vertices).
    _result, surf = worker.call("solve", {**pose, "answer": "surface"}, shared=shared)
    assert surf["surface"].dtype == np.float32 and np.allclose(surf["surface"], out["deformed_vertices"], atol=1e-5)

    worker.stop()
    worker.call("solve", pose, shared=shared)  # a fresh process: it holds nothing
    assert sorted(loads) == ["cage", "embedding", "regions"]


def test_a_worker_that_dropped_shared_content_gets_it_again(worker):
    """The client believes the worker holds a cage it does not (it dropped it, or another client
    sent it): the worker answers "missing" and the client sends it with the same request."""
    loads = []
    _V, _top, shared = _box_session(loads)
    pose = {"mode": "AFFINE", "transforms": [_lift(0.2)], "handle_names": ["Lift"]}
    worker.ensure_started()
    worker._given.add(("cage", shared["cage"][0]))  # never sent to this worker
    result, out = worker.call("solve", pose, shared=shared)
    assert sorted(loads) == ["cage", "embedding", "regions"]  # the cage on the second try
    assert [op for op, _n in worker.sent] == ["solve", "solve"]
    async_done = []
    worker._given.add(("regions", "not-sent"))
    worker.submit(
        "solve",
        pose,
        shared={**shared, "regions": ("not-sent", shared["regions"][1])},
        on_done=lambda r, a: async_done.append(a),
        on_error=lambda e: async_done.append(e),
    )
    import time

    deadline = time.time() + 60
    while not async_done and time.time() < deadline:
        worker.drain()
        time.sleep(0.01)
    assert isinstance(async_done[0], dict) and "deformed_vertices" in async_done[0]


def test_bad_shared_content_is_a_clear_error_and_the_worker_lives_on(worker):
    from blender_nerf_deform.addon.worker.client import WorkerError

    loads = []
    V, _top, shared = _box_session(loads)
    bad = V.copy()
    bad[3] = np.nan
    cage_key, _load = shared["cage"]
    shared = {**shared, "cage": ("nan-cage", lambda: {"vertices": bad, "tets": _box_tets()})}
    with pytest.raises(WorkerError, match="cage vertices must be finite") as error:
        worker.call("solve", {"mode": "ARAP", "transforms": [_lift(0.1)]}, shared=shared)
    assert error.value.kind == "input"
    assert worker.call("info")[0]["pid"] == worker._proc.pid


def _box_tets():
    from blender_nerf_deform.engine.geometry.cage import box_cage

    return box_cage((3, 3, 3), (-1, -1, -1), (1, 1, 1))[1]
