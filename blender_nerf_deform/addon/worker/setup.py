"""Set Up Worker: the add-on makes the Python environment its engine worker runs in.

The engine needs torch and a dozen other packages that Blender's Python does not have and
must not get (docs/ARCHITECTURE.md: the add-on never imports torch). After the user confirms, this
creates a virtual environment under the extension's user folder
(`bpy.utils.extension_path_user(<package>, path="worker-env")`, never the extension's own
folder, which Blender replaces on update), installs the engine's pinned requirements
(`engine/requirements.txt`, the file `make setup` installs for the tests) and sets Worker
Python to it.

Which Python the environment is made from: Blender's own when it is 3.11 (Blender 4.2-5.0;
it is always there, and it ships venv and ensurepip), else a python3.11 found on the system
(Blender 5.1+ ships 3.13, for which the pinned pytetwild 0.2.3 has no wheel), or the one the
user names (preferences: Base Python). The worker is a separate process, so its Python need
not be Blender's; it must only be one the pins have wheels for.

Torch's build comes from its package index: PyPI's torch on Linux is the CUDA build (about
2.5 GB with its NVIDIA libraries), so a CPU build on Linux and Windows is installed from
PyTorch's CPU index first; "pip" as the torch source uses pip's own configuration (a mirror
or a wheel cache) for torch too. Everything else comes from pip's configured index.

Nothing half-made is ever used: the environment is built in `worker-env.partial` and only
renamed into place once every package imports and matches its pin, so a failed, cancelled
or offline setup leaves the previous environment and the Worker Python preference as they
were. An environment already there is checked and reused (mode Reuse / Auto) or rebuilt.
From the preferences the setup runs in the background (a thread that runs venv and pip as
child processes; a modal timer shows progress, Esc or Cancel stops it); from Python,
`bpy.ops.nerf_deform.setup_worker()` blocks. Everything pip prints goes to
`worker-env-setup.log` beside the environment (each setup appends).
"""

from __future__ import annotations

import collections
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..data.paths import ADDON_PACKAGE, addon_preferences
from . import client as worker_client
from .client import PACKAGE_DIR

REQUIREMENTS = PACKAGE_DIR / "engine" / "requirements.txt"
ENV_NAME = "worker-env"
LOG_NAME = "worker-env-setup.log"
PYTHON_VERSION = (3, 11)  # what the pins in engine/requirements.txt have wheels for
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"
TORCH_CUDA_WINDOWS_INDEX = "https://download.pytorch.org/whl/cu128"
DOWNLOAD_SIZE = "about 1 GB"
# Module names to import to prove an environment can run the worker (package name → module).
IMPORTS = {
    "torch": "torch",
    "numpy": "numpy",
    "scipy": "scipy",
    "scikit-image": "skimage",
    "trimesh": "trimesh",
    "libigl": "igl",
    "pytetwild": "pytetwild",
    "numba": "numba",
    "pillow": "PIL",
    "pycolmap": "pycolmap",
}
_NETWORK_SIGNS = (
    "NewConnectionError",
    "Failed to establish a new connection",
    "Name or service not known",
    "Temporary failure in name resolution",
    "Network is unreachable",
    "ConnectTimeoutError",
    "Connection refused",
    "No matching distribution found",
)


class SetupError(Exception):
    """The setup cannot go on; the message says what is wrong and what to do."""


class SetupCancelled(Exception):
    pass


def user_folder(create: bool = True) -> Path:
    """Where the environment goes: the extension's user folder (a temporary one when the add-on was
    imported directly rather than enabled as an extension, which has no user folder)."""
    try:
        return Path(bpy.utils.extension_path_user(ADDON_PACKAGE, create=create))
    except (ValueError, AttributeError):
        import tempfile

        return Path(tempfile.gettempdir()) / "nerf_deform_user"


def env_python(env: Path) -> Path:
    return env / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def pins(path: Path = REQUIREMENTS) -> dict[str, str]:
    """{package: version} of the `name==version` lines of a requirements file."""
    found = {}
    for line in path.read_text().splitlines():
        m = re.match(r"\s*([A-Za-z0-9_.-]+)\s*==\s*([^\s;#]+)", line)
        if m:
            found[m.group(1).lower()] = m.group(2)
    return found


def _python_version(python: str) -> tuple[int, int] | None:
    """(major, minor) of an interpreter that has venv and ensurepip, else None."""
    try:
        proc = subprocess.run(
            [python, "-c", "import sys, venv, ensurepip; print(*sys.version_info[:2])"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    if proc.returncode != 0:
        return None
    major, minor = proc.stdout.split()[:2]
    return int(major), int(minor)


def base_python_candidates(preferred: str = "") -> list[str]:
    """Interpreters to make the environment from, best first (see the module docstring)."""
    found = [preferred, sys.executable]
    found += [shutil.which(f"python{PYTHON_VERSION[0]}.{PYTHON_VERSION[1]}") or ""]
    found += [
        f"/usr/bin/python{PYTHON_VERSION[0]}.{PYTHON_VERSION[1]}",
        f"/usr/local/bin/python{PYTHON_VERSION[0]}.{PYTHON_VERSION[1]}",
        f"/opt/homebrew/bin/python{PYTHON_VERSION[0]}.{PYTHON_VERSION[1]}",
    ]
    unique = []
    for python in found:
        if python and python not in unique and os.path.isfile(python):
            unique.append(python)
    return unique


def find_base_python(preferred: str = "") -> str:
    tried = []
    for python in base_python_candidates(preferred):
        version = _python_version(python)
        if version == PYTHON_VERSION:
            return python
        tried.append(f"{python} ({f'Python {version[0]}.{version[1]}' if version else 'no venv/ensurepip'})")
        if python == preferred:
            what = f"Python {version[0]}.{version[1]}" if version else "not a Python with venv and ensurepip"
            raise SetupError(
                f"Base Python {preferred} is {what}; the worker's packages need "
                f"Python {PYTHON_VERSION[0]}.{PYTHON_VERSION[1]} with venv"
            )
    raise SetupError(
        f"no Python {PYTHON_VERSION[0]}.{PYTHON_VERSION[1]} with venv found (tried {', '.join(tried) or 'none'}): "
        f"install one, or name it in NeRF Deform's preferences (Base Python)"
    )


def torch_index(build: str, source: str, custom: str = "") -> str:
    """The index torch is installed from ("" : pip's own configuration, as for every other package)."""
    if source == "PIP":
        return ""
    if source == "CUSTOM":
        if not custom.strip():
            raise SetupError("Torch Source is Custom but Torch Index is empty: give the index URL")
        return custom.strip()
    if build == "CPU":
        return "" if sys.platform == "darwin" else TORCH_CPU_INDEX  # PyPI's macOS torch is the CPU (MPS) build
    return TORCH_CUDA_WINDOWS_INDEX if os.name == "nt" else ""  # PyPI's Linux torch is the CUDA build


_CHECK = """
import importlib, importlib.metadata as md, json, sys
pins, imports, root, package = json.loads(sys.argv[1])
out = {"python": sys.executable, "version": "%d.%d" % sys.version_info[:2], "mismatched": {}, "missing": []}
for name, want in pins.items():
    try:
        have = md.version(name)
    except md.PackageNotFoundError:
        out["missing"].append(name)
        continue
    if have.split("+")[0] != want:
        out["mismatched"][name] = have
for name, module in imports.items():
    try:
        importlib.import_module(module)
    except Exception as exc:
        out["missing"].append(f"{name} ({type(exc).__name__}: {exc})")
torch = importlib.import_module("torch")  # in the worker environment's Python, not Blender's
out["torch"] = torch.__version__
out["cuda"] = bool(torch.cuda.is_available())
sys.path.insert(0, root)
importlib.import_module(package + ".engine.service.ops")  # the worker's own imports
print("NERF_DEFORM_CHECK " + json.dumps(out))
"""


def check_environment(python: Path) -> dict:
    """What the environment holds: {"ok", "problem", "torch", "cuda", ...}; ok when every pinned package
    is there at its pin, imports, and the engine's worker ops import."""
    if not python.is_file():
        return {"ok": False, "problem": f"{python} does not exist"}
    args = json.dumps([pins(), IMPORTS, str(PACKAGE_DIR.parent), PACKAGE_DIR.name])
    try:
        proc = subprocess.run([str(python), "-c", _CHECK, args], capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return {"ok": False, "problem": f"{python} does not run: {exc}"}
    line = next((out for out in proc.stdout.splitlines() if out.startswith("NERF_DEFORM_CHECK ")), None)
    if proc.returncode != 0 or line is None:
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"ok": False, "problem": f"{python} cannot import the engine: {last}"}
    info = json.loads(line.split(" ", 1)[1])
    problems = [f"missing {', '.join(info['missing'])}"] if info["missing"] else []
    if info["mismatched"]:
        want = pins()
        problems.append(
            "not at the pinned version: "
            + ", ".join(f"{k} {v} (wants {want[k]})" for k, v in info["mismatched"].items())
        )
    return {**info, "ok": not problems, "problem": "; ".join(problems)}


class SetupJob:
    """One setup: build (or reuse) the environment in `folder`. `run()` blocks; `start()` runs it in a
    thread. The state (`progress`, `message`, `log`, `done`, `error`, `python`, `reused`) is read by
    the main thread; nothing here touches Blender's data (the operator sets the preference)."""

    def __init__(
        self,
        folder: Path,
        mode: str = "AUTO",
        build: str = "CPU",
        torch_source: str = "AUTO",
        torch_index_url: str = "",
        base_python: str = "",
    ):
        self.folder = Path(folder)
        self.env = self.folder / ENV_NAME
        self.staging = self.folder / f"{ENV_NAME}.partial"
        self.log_path = self.folder / LOG_NAME
        self.mode, self.build = mode, build
        self.torch_source, self.torch_index_url, self.base_python = torch_source, torch_index_url, base_python
        self.progress, self.message = 0.0, "starting"
        self.log: collections.deque[str] = collections.deque(maxlen=200)
        self.done: str | None = None  # "ok" | "error" | "cancelled"
        self.error = ""
        self.python: str | None = None
        self.reused = False
        self.info: dict = {}
        self._cancel = threading.Event()
        self._proc: subprocess.Popen | None = None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    # -- control
    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="nerf-deform-worker-setup", daemon=True)
        self._thread.start()

    def cancel(self) -> None:
        self._cancel.set()
        with self._lock:
            proc = self._proc
        if proc is not None and proc.poll() is None:
            try:  # pip may have children (builds): stop the whole group
                os.killpg(proc.pid, signal.SIGTERM) if os.name != "nt" else proc.terminate()
            except OSError:
                pass

    def wait(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    # -- the work
    def run(self) -> None:
        try:
            self._run()
            self.done, self.progress = "ok", 1.0
        except SetupCancelled:
            self.done, self.message = "cancelled", "cancelled: nothing changed"
        except SetupError as exc:
            self.done, self.error = "error", str(exc)
        except Exception as exc:  # a bug: still a report, never a traceback in Blender's face
            self.done, self.error = "error", f"{type(exc).__name__}: {exc} (see {self.log_path})"
            self._log(repr(exc))
        finally:
            if self.done != "ok":
                shutil.rmtree(self.staging, ignore_errors=True)
            self._close_log()

    def _say(self, progress: float, message: str) -> None:
        self.progress, self.message = progress, message
        self._log(f"== {message}")

    def _log(self, line: str) -> None:
        self.log.append(line)
        if getattr(self, "_log_file", None) is not None:
            self._log_file.write(line + "\n")
            self._log_file.flush()

    def _close_log(self) -> None:
        if getattr(self, "_log_file", None) is not None:
            self._log_file.close()
            self._log_file = None

    def _check_cancel(self) -> None:
        if self._cancel.is_set():
            raise SetupCancelled()

    def _run(self) -> None:
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            self._log_file = open(self.log_path, "a", encoding="utf-8")
        except OSError as exc:
            raise SetupError(f"cannot write in {self.folder}: {exc.strerror or exc}") from exc
        import time

        self._log(f"=== Set Up Worker, {time.strftime('%Y-%m-%d %H:%M:%S')}, mode {self.mode}, build {self.build}")
        if self.mode in ("AUTO", "REUSE") and env_python(self.env).exists():
            self._say(0.02, f"checking the environment at {self.env}")
            info = check_environment(env_python(self.env))
            if info["ok"]:
                self._compile(str(env_python(self.env)), 0.5)  # a moment when the cache is already filled
                self.info, self.reused, self.python = info, True, str(env_python(self.env))
                self._say(1.0, f"reusing {self.env} (torch {info['torch']}, {'CUDA' if info['cuda'] else 'CPU'})")
                return
            if self.mode == "REUSE":
                raise SetupError(f"the environment at {self.env} is not usable ({info['problem']}): rebuild it")
            self._log(f"the environment at {self.env} is not usable ({info['problem']}): rebuilding it")
        elif self.mode == "REUSE":
            raise SetupError(f"there is no environment at {self.env} to reuse: set one up")
        index = torch_index(self.build, self.torch_source, self.torch_index_url)
        base = find_base_python(self.base_python)
        self._check_cancel()
        shutil.rmtree(self.staging, ignore_errors=True)  # what an interrupted setup left
        self._say(0.03, f"creating a Python environment from {base}")
        self._command([base, "-m", "venv", str(self.staging)], 0.03, 0.06, "creating the environment")
        python = str(env_python(self.staging))
        pip = [python, "-m", "pip", "install", "--disable-pip-version-check", "--progress-bar", "off"]
        if index:
            torch_pin = pins()["torch"]
            self._say(0.06, f"installing torch {torch_pin} ({self.build}) from {index}")
            self._command(pip + [f"torch=={torch_pin}", "--index-url", index], 0.06, 0.5, "installing torch")
        self._say(0.5 if index else 0.06, "installing the engine's packages")
        self._command(pip + ["-r", str(REQUIREMENTS)], 0.5 if index else 0.06, 0.92, "installing")
        self._say(0.93, "checking that the engine imports")
        info = check_environment(env_python(self.staging))
        if not info["ok"]:
            raise SetupError(f"the new environment is not usable: {info['problem']} (log: {self.log_path})")
        self._compile(python, 0.94)
        self._check_cancel()
        self._say(0.98, f"moving the environment into {self.env}")
        self._replace_env()
        self.info, self.python = info, str(env_python(self.env))
        self._say(1.0, f"done: torch {info['torch']} ({'CUDA' if info['cuda'] else 'CPU'}) in {self.env}")

    def _compile(self, python: str, start: float) -> None:
        """The engine's `compile`: its CPU kernels into the cache the worker reads, so the artist's
        first frame does not wait for them (compiling costs several times a frame)."""
        self._say(start, "compiling the engine's kernels (once)")
        env, _work = worker_client.worker_environment(inherit_pythonpath=False)
        self._command(
            [python, "-m", f"{PACKAGE_DIR.name}.engine", "compile"], start, 0.98, "compiling the kernels", env=env
        )

    def _replace_env(self) -> None:
        """Rename the finished environment into place; the old one is kept until the new one is there."""
        old = self.folder / f"{ENV_NAME}.old"
        shutil.rmtree(old, ignore_errors=True)
        if self.env.exists():
            os.replace(self.env, old)
        try:
            os.replace(self.staging, self.env)
        except OSError:
            if old.exists():
                os.replace(old, self.env)
            raise
        shutil.rmtree(old, ignore_errors=True)

    def _command(self, argv: list[str], start: float, end: float, what: str, env: dict | None = None) -> None:
        """Run one step, its output into the log; progress moves from `start` towards `end` with each
        package pip collects. Raises SetupError naming what went wrong (no network, a missing wheel).
        `env`: the child's environment (default: Blender's, without its Python paths)."""
        self._check_cancel()
        self._log("$ " + " ".join(argv))
        if env is None:
            env = dict(os.environ, PYTHONUNBUFFERED="1")
            env.pop("PYTHONPATH", None)  # Blender's own paths must not leak into the new environment
            env.pop("PYTHONHOME", None)
        try:
            proc = subprocess.Popen(
                argv,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                env=env,
                start_new_session=(os.name != "nt"),
            )
        except OSError as exc:
            raise SetupError(f"{what}: cannot run {argv[0]}: {exc.strerror or exc}") from exc
        with self._lock:
            self._proc = proc
        collected, lines = 0, []
        for line in proc.stdout:
            line = line.rstrip()
            self._log(line)
            lines.append(line)
            if line.startswith(("Collecting ", "Processing ")):  # a package from the index, or a local file
                collected += 1
                self.progress = start + (end - start) * 0.9 * (1.0 - 0.9**collected)
                self.message = f"{what}: {os.path.basename(line.split(' ', 2)[1])}"
            elif line.startswith("Installing collected packages"):
                self.progress, self.message = start + (end - start) * 0.92, f"{what}: unpacking"
        code = proc.wait()
        with self._lock:
            self._proc = None
        self._check_cancel()
        if code != 0:
            errors = [out for out in lines if out.startswith("ERROR")] or lines[-1:] or ["no output"]
            if any(sign in out for out in lines for sign in _NETWORK_SIGNS):
                raise SetupError(
                    f"{what}: the package index cannot be reached (no network?): {errors[-1]} (log: {self.log_path})"
                )
            raise SetupError(f"{what} failed: {errors[-1]} (log: {self.log_path})")


# --------------------------------------------------------------------------- Blender side

_job: SetupJob | None = None  # the setup running now (one at a time), shown in the preferences


def running_job() -> SetupJob | None:
    return _job if _job is not None and _job.done is None else None


def existing_environment() -> Path | None:
    env = user_folder(create=False) / ENV_NAME
    return env if env_python(env).exists() else None


_MODES = (
    ("AUTO", "Auto", "Reuse a working environment if there is one, else build one"),
    ("REUSE", "Reuse", "Check the existing environment and use it"),
    ("REBUILD", "Rebuild", "Build a new environment (the old one stays until the new one works)"),
)


class NERFDEFORM_OT_setup_worker(bpy.types.Operator):
    """Make a Python environment for the NeRF engine (torch and the engine's packages, downloaded from the package index) and set Worker Python to it"""  # noqa: E501 (the tooltip: one line)

    bl_idname = "nerf_deform.setup_worker"
    bl_label = "Set Up Worker"
    bl_options = {"REGISTER"}

    mode: EnumProperty(name="Mode", items=_MODES, default="AUTO")
    folder: StringProperty(
        name="Folder",
        subtype="DIR_PATH",
        options={"SKIP_SAVE"},
        description="Where the environment goes (empty: the extension's user folder)",
    )
    background: BoolProperty(options={"HIDDEN", "SKIP_SAVE"}, default=False)  # set by invoke: run in a thread

    def _settings(self, context) -> dict:
        prefs = addon_preferences(context)
        if prefs is None:
            return {"build": "CPU", "torch_source": "AUTO", "torch_index_url": "", "base_python": ""}
        return {
            "build": prefs.worker_build,
            "torch_source": prefs.torch_source,
            "torch_index_url": prefs.torch_index_url,
            "base_python": bpy.path.abspath(prefs.base_python),
        }

    def _job(self, context) -> SetupJob:
        if running_job() is not None:
            raise SetupError("a worker setup is already running")
        client = worker_client._client
        if self.mode != "REUSE" and client is not None and client.busy:
            raise SetupError("the worker is busy (training or rendering): wait for it or cancel its job first")
        folder = Path(bpy.path.abspath(self.folder)) if self.folder else user_folder()
        return SetupJob(folder, self.mode, **self._settings(context))

    def _finish(self, context, job: SetupJob) -> set[str]:
        if job.done == "cancelled":
            self.report({"WARNING"}, "Set Up Worker cancelled: the previous Worker Python is unchanged")
            return {"CANCELLED"}
        if job.done != "ok":
            self.report({"ERROR"}, f"Set Up Worker: {job.error}")
            return {"CANCELLED"}
        prefs = addon_preferences(context)
        if worker_client._client is not None and not job.reused:
            worker_client.shutdown()  # it ran the environment that was just replaced
        if prefs is not None:
            prefs.worker_python = job.python
        how = "reused" if job.reused else "set up"
        self.report(
            {"INFO"},
            f"Worker environment {how}: torch {job.info.get('torch')} "
            f"({'CUDA' if job.info.get('cuda') else 'CPU'}); Worker Python = {job.python}"
            + ("" if prefs is not None else " (the add-on is not enabled: no preference to set)"),
        )
        return {"FINISHED"}

    def execute(self, context):
        global _job
        try:
            _job = job = self._job(context)
        except SetupError as exc:
            self.report({"ERROR"}, f"Set Up Worker: {exc}")
            return {"CANCELLED"}
        if self.background:
            job.start()
            wm = context.window_manager
            self._timer = wm.event_timer_add(0.25, window=context.window)
            wm.modal_handler_add(self)
            return {"RUNNING_MODAL"}
        job.run()
        print(f"Set Up Worker: {job.message}")
        return self._finish(context, job)

    def invoke(self, context, event):
        self.background = True
        return context.window_manager.invoke_props_dialog(
            self,
            width=420,
            title="Set Up the NeRF Worker",
            confirm_text="Download and Install" if self.mode != "REUSE" else "Reuse",
        )

    def draw(self, context):
        col = self.layout.column(align=True)
        env = existing_environment() if not self.folder else None
        if self.mode != "REUSE":
            col.label(text=f"Downloads {DOWNLOAD_SIZE} from the package index", icon="INFO")
            col.label(text="(torch and the engine's packages) into the extension's user folder.")
        if env is not None:
            col.label(text=f"Found an environment: {env}")
            col.prop(self, "mode", expand=True)

    def modal(self, context, event):
        job = _job
        if event.type == "ESC":
            job.cancel()
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        _redraw_preferences(context)
        if job.done is None:
            context.workspace.status_text_set(f"Set Up Worker: {100 * job.progress:.0f}% {job.message} (Esc to cancel)")
            return {"RUNNING_MODAL"}
        context.window_manager.event_timer_remove(self._timer)
        context.workspace.status_text_set(None)
        return self._finish(context, job)


class NERFDEFORM_OT_cancel_worker_setup(bpy.types.Operator):
    """Stop the running worker setup (nothing changes: the previous Worker Python stays)"""

    bl_idname = "nerf_deform.cancel_worker_setup"
    bl_label = "Cancel Setup"

    @classmethod
    def poll(cls, context):
        return running_job() is not None

    def execute(self, context):
        running_job().cancel()
        return {"FINISHED"}


def _redraw_preferences(context) -> None:
    for window in context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "PREFERENCES":
                area.tag_redraw()


def last_job() -> SetupJob | None:
    """The latest setup of this session, running or over (its `done` and `error` say how it ended)."""
    return _job


_classes = (NERFDEFORM_OT_setup_worker, NERFDEFORM_OT_cancel_worker_setup)
_register, _unregister = bpy.utils.register_classes_factory(_classes)


def register():
    _register()


def unregister():
    job = running_job()
    if job is not None:
        job.cancel()
        job.wait(30)
    _unregister()
