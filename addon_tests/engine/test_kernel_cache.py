"""numba's kernel cache (engine/kernel_cache.py): every copy of the same engine reads one cache, and a
kernel file's change makes every cached kernel of its stage stale."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys

from fixtures import REPO

from blender_nerf_deform.engine import kernel_cache

# One cheap kernel (no torch): the lazy Adam, run on a 4x2 table.
_RUN_ADAM = """
import numpy as np
from blender_nerf_deform.engine.nerf.adam_kernels import sparse_adam
z = np.zeros((4, 2), np.float32)
sparse_adam(z.copy(), z.copy(), z.copy(), z.copy(), np.ones(4, np.uint8), 1e-2, 0.9, 0.99, 1e-15, 0.1, 0.01)
"""


def _run_adam(cwd, cache):
    """Run the kernel in a fresh process in `cwd` with numba's cache in `cache` (None: beside the source)."""
    env = dict(os.environ, NUMBA_DEBUG_CACHE="1")
    if cache is None:
        env.pop("NUMBA_CACHE_DIR", None)
    else:
        env["NUMBA_CACHE_DIR"] = str(cache)
    env.pop("PYTHONPATH", None)  # the package is found in cwd: the copy there, not the repository
    proc = subprocess.run(
        [sys.executable, "-c", _RUN_ADAM], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout + proc.stderr


def test_every_kernel_module_is_a_kernel_file_that_imports_only_its_stage():
    engine = kernel_cache.ENGINE_ROOT
    kernels = set(kernel_cache.kernel_files())
    for path in engine.rglob("*.py"):
        text = path.read_text()
        if "cache=True" in text:  # numba's cache: the digest must cover it
            assert path in kernels, f"{path} caches kernels but is not named *{kernel_cache.KERNEL_SUFFIX}"
    for path in kernels:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                names = [node.module] if node.module else [a.name for a in node.names]
                for name in names:
                    if node.level == 1:  # the same stage: only its kernel files (Triton's hold no numba cache)
                        assert name.endswith(("_kernels", "_triton")), f"{path.name} imports .{name}"
                    else:
                        assert node.level == 2 and name in ("backend", "kernel_cache"), (
                            f"{path.name} imports {'.' * node.level}{name}"
                        )


def _copy_engine(to):
    shutil.copytree(
        REPO / "blender_nerf_deform", to / "blender_nerf_deform", ignore=shutil.ignore_patterns("__pycache__")
    )
    return to / "blender_nerf_deform" / "engine"


def test_a_copy_of_the_engine_reads_the_kernels_another_copy_compiled_until_its_stage_changes(tmp_path):
    cache = tmp_path / "cache"
    first = _run_adam(REPO, cache)
    assert "data saved" in first and "adam_kernels" in first
    # The shared place is named by the kernel's package, not by its copy's path.
    assert (cache / "blender_nerf_deform.engine.nerf").is_dir()

    copy = tmp_path / "copy"
    engine = _copy_engine(copy)
    second = _run_adam(copy, cache)
    assert "data loaded" in second and "data saved" not in second, second[-2000:]

    # Another kernel file of the stage changes (not the one run): the kernel is compiled again.
    with open(engine / "nerf" / "march_kernels.py", "a") as f:
        f.write("\n# changed\n")
    third = _run_adam(copy, cache)
    assert "data saved" in third, third[-2000:]


def test_without_a_cache_folder_kernels_stay_beside_their_source_and_follow_their_stage(tmp_path):
    engine = _copy_engine(tmp_path)
    assert "data saved" in _run_adam(tmp_path, None)
    assert list((engine / "nerf" / "__pycache__").glob("adam_kernels.sparse_adam-*.nbi"))
    again = _run_adam(tmp_path, None)
    assert "data loaded" in again and "data saved" not in again, again[-2000:]
    with open(engine / "nerf" / "march_kernels.py", "a") as f:  # numba's own stamp would not see this
        f.write("\n# changed\n")
    assert "data saved" in _run_adam(tmp_path, None)


def test_a_stage_s_digest_follows_its_kernel_files_only(tmp_path):
    stage = tmp_path / "stage"
    stage.mkdir()
    (stage / "a_kernels.py").write_text("x = 1\n")
    (stage / "helper.py").write_text("y = 1\n")
    before = kernel_cache.kernels_digest.__wrapped__(stage)
    (stage / "helper.py").write_text("y = 2\n")
    assert kernel_cache.kernels_digest.__wrapped__(stage) == before
    (stage / "a_kernels.py").write_text("x = 2\n")
    assert kernel_cache.kernels_digest.__wrapped__(stage) != before
