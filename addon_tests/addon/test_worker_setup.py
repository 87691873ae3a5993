"""Set Up Worker (addon/worker/setup.py): a real environment, built by pip from the package index.

The extension is installed and enabled as Blender enables extensions, so the operator sets
the real Worker Python preference. The environment is built once per module into a temporary
folder (pip's own configuration and cache: the project's CI has the wheels cached by
`make setup`; the full download is timed by tools/bench/worker_setup.py, BENCHMARKS.md).
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO_MODULE = "nerf_deform_setup_test"
EXT_MODULE = f"bl_ext.{REPO_MODULE}.blender_nerf_deform"

pytestmark = pytest.mark.slow


@pytest.fixture
def enabled(blender, extension_zip, tmp_path):
    """The extension installed from its zip and enabled; yields (bpy, its preferences, its worker_setup module)."""
    bpy = blender
    bpy.context.preferences.extensions.repos.new(
        name="NeRF Deform Setup Test", module=REPO_MODULE, custom_directory=str(tmp_path / "repo"), source="USER"
    )
    assert bpy.ops.extensions.package_install_files(
        filepath=str(extension_zip), repo=REPO_MODULE, enable_on_install=True
    ) == {"FINISHED"}
    prefs = bpy.context.preferences.addons[EXT_MODULE].preferences
    yield bpy, prefs, sys.modules[f"{EXT_MODULE}.addon.worker.setup"]
    bpy.ops.preferences.addon_disable(module=EXT_MODULE)


@pytest.fixture(scope="module")
def env_folder(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("worker_user_folder")


def _ensure_env(worker_setup, folder: Path) -> Path:
    """The module's environment (built by the first test; rebuilt here if that test did not run)."""
    job = worker_setup.SetupJob(folder, "AUTO", torch_source="PIP")
    job.run()
    assert job.done == "ok", job.error
    return Path(job.python)


def _imports_torch(python: Path) -> str:
    proc = subprocess.run(
        [
            str(python),
            "-c",
            "import torch, scipy, skimage, trimesh, igl, pytetwild, numba, pycolmap; print(torch.__version__)",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


def test_setup_creates_the_environment_and_sets_worker_python(enabled, env_folder):
    bpy, prefs, worker_setup = enabled
    prefs.torch_source = "PIP"  # this machine's pip configuration holds the CPU torch wheel
    assert prefs.worker_python == ""
    assert bpy.ops.nerf_deform.setup_worker(folder=str(env_folder), mode="AUTO") == {"FINISHED"}
    python = env_folder / "worker-env" / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    assert Path(prefs.worker_python) == python
    assert _imports_torch(python).startswith(worker_setup.pins()["torch"])
    assert not (env_folder / "worker-env.partial").exists()
    assert worker_setup.check_environment(python)["ok"]
    # Last, the engine's kernels were compiled into the cache the worker reads (engine `compile`).
    assert "the kernels are compiled" in (env_folder / "worker-env-setup.log").read_text()
    # The environment really runs the worker: the add-on's own client starts on it and answers.
    client = sys.modules[f"{EXT_MODULE}.addon.worker.jobs"].worker(bpy.context)
    try:
        hello = client.ensure_started()
        assert hello["torch"].startswith(worker_setup.pins()["torch"])
    finally:
        client.stop()

    # A second press finds the environment and reuses it: no pip, same files.
    marker = python.parent.parent / "pyvenv.cfg"
    before = marker.stat().st_mtime_ns
    started = time.perf_counter()
    assert bpy.ops.nerf_deform.setup_worker(folder=str(env_folder), mode="AUTO") == {"FINISHED"}
    assert marker.stat().st_mtime_ns == before
    log = (env_folder / "worker-env-setup.log").read_text()
    assert log.rstrip().splitlines()[-1].startswith("== reusing")
    assert "pip" not in log.split("=== Set Up Worker")[-1]
    assert time.perf_counter() - started < 120  # a check, not a rebuild (a rebuild downloads ~1 GB)
    assert Path(prefs.worker_python) == python


def test_the_default_folder_is_the_extensions_user_folder(enabled):
    bpy, _, worker_setup = enabled
    folder = worker_setup.user_folder()
    assert Path(bpy.utils.extension_path_user(EXT_MODULE)) == folder
    assert Path(os.environ["BLENDER_USER_RESOURCES"]) in folder.parents
    assert worker_setup.REQUIREMENTS.is_file()  # shipped inside the extension


def test_cancelled_setup_leaves_the_old_environment_and_preference(enabled, env_folder):
    bpy, prefs, worker_setup = enabled
    python = _ensure_env(worker_setup, env_folder)
    prefs.torch_source = "PIP"
    prefs.worker_python = "/previous/python"

    def cancel_when_pip_runs():
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            job = worker_setup._job
            if job is not None and job.done is None and job.message.startswith("installing:"):
                job.cancel()
                return
            time.sleep(0.05)

    canceller = threading.Thread(target=cancel_when_pip_runs)
    canceller.start()
    result = bpy.ops.nerf_deform.setup_worker(folder=str(env_folder), mode="REBUILD")
    canceller.join()
    assert result == {"CANCELLED"}
    assert worker_setup._job.done == "cancelled"
    assert prefs.worker_python == "/previous/python"
    assert not (env_folder / "worker-env.partial").exists()
    assert worker_setup.check_environment(python)["ok"]


def test_no_network_is_a_clear_report_and_changes_nothing(enabled, env_folder, monkeypatch, capsys):
    bpy, prefs, worker_setup = enabled
    python = _ensure_env(worker_setup, env_folder)
    prefs.worker_python = str(python)
    prefs.torch_source = "PIP"
    # No pip configuration, no cache, no local wheels, an index nobody answers on.
    monkeypatch.setenv("PIP_CONFIG_FILE", os.devnull)
    monkeypatch.setenv("PIP_INDEX_URL", "http://127.0.0.1:9/simple")
    monkeypatch.setenv("PIP_NO_CACHE_DIR", "1")
    monkeypatch.setenv("PIP_RETRIES", "0")
    monkeypatch.setenv("PIP_TIMEOUT", "3")
    for name in ("PIP_FIND_LINKS", "PIP_EXTRA_INDEX_URL"):
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(RuntimeError) as error:
        bpy.ops.nerf_deform.setup_worker(folder=str(env_folder), mode="REBUILD")
    message = str(error.value)
    assert "package index cannot be reached" in message and "Traceback" not in message
    assert worker_setup._job.done == "error"
    assert prefs.worker_python == str(python)
    assert not (env_folder / "worker-env.partial").exists()
    assert worker_setup.check_environment(python)["ok"]


def test_reuse_without_an_environment_and_a_wrong_base_python_are_clear(enabled, tmp_path):
    bpy, prefs, worker_setup = enabled
    with pytest.raises(RuntimeError, match="no environment at .* to reuse"):
        bpy.ops.nerf_deform.setup_worker(folder=str(tmp_path / "empty"), mode="REUSE")
    prefs.base_python = "/bin/sh"
    with pytest.raises(RuntimeError, match="Base Python /bin/sh is not a Python with venv"):
        bpy.ops.nerf_deform.setup_worker(folder=str(tmp_path / "empty"), mode="REBUILD")
    # A folder that cannot be made (its parent is a file: fails for every user, root included).
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    prefs.base_python = ""
    with pytest.raises(RuntimeError, match="cannot write in"):
        bpy.ops.nerf_deform.setup_worker(folder=str(blocker / "env"), mode="AUTO")
    assert prefs.worker_python == ""
