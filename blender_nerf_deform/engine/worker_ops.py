"""The requests the worker serves, one handler per op (registered with `worker.op`).

Each handler turns plain params and numpy arrays into an engine call. Loaded
models are cached by path and modification time, so a render per frame does
not re-read the checkpoint.
"""

from __future__ import annotations

import os

from .errors import EngineError
from .worker import Job, op

_models: dict[tuple[str, str], tuple[float, object]] = {}


def cached_model(path: str, device: str = "auto"):
    """The NeRF at `path`, loaded once per (path, device) and reloaded when the file changes."""
    from .checkpoint import load_nerf

    try:
        mtime = os.path.getmtime(path)
    except OSError:
        raise EngineError(f"NeRF checkpoint {path} does not exist or cannot be read") from None
    key = (os.path.abspath(path), device)
    cached = _models.get(key)
    if cached is None or cached[0] != mtime:
        _models[key] = (mtime, load_nerf(path, device=device))
    return _models[key][1]


@op("load")
def load(job: Job) -> dict:
    """Read a checkpoint: its bounds and configuration, for placing it in the scene."""
    model = cached_model(job.params["path"], job.params.get("device", "auto"))
    return {
        "aabb": [float(x) for x in model.aabb.reshape(-1).tolist()],
        "config": model.config.to_dict(),
        "device": str(model.device),
    }
