"""Capture Dataset: a NeRF dataset of the selected objects, rendered from the current scene.

What BlenderNeRF does, with the project's own capture code (`dataset.py`, the same that
`tools/make_dataset.py` runs): cameras on a sphere or the upper hemisphere (or above a minimum
elevation) around the selected objects, looking at the centre of their evaluated world bounding
box, at a radius that fits them in the picture (or the one given); each view rendered by the
scene's own render engine (or Cycles on the CPU) as a straight-alpha RGBA PNG (or opaque RGB
with the background); `transforms.json` in Blender's world frame with the selection's padded
bounds as `aabb`, so the NeRF trained on it lands exactly on the objects it was made from. When
done, the dataset folder is put into the Train panel's Dataset field: Train NeRF is the next click.

How it runs:

- The current file (as it is in memory, saved or not) is saved as a copy to a temporary .blend
  (`wm.save_as_mainfile(copy=True)`: relative paths are remapped to stay valid, and the open
  file keeps its own path and unsaved state), and a separate Blender process renders it:
  `blender -b --factory-startup COPY.blend --python capture/runner.py -- CONFIG.json`, or, with
  the `bpy` module (no Blender binary), `python capture/runner.py CONFIG.json`. Blender's UI
  stays usable meanwhile, the user can keep editing (the capture shows the scene as it was when
  it started), and a crash of the renderer leaves Blender untouched. The factory-started
  renderer has Blender's own engines (Cycles, EEVEE, Workbench) and none of the user's add-ons,
  so a scene whose engine an add-on provides is refused up front (pick Cycles). Nor has it the
  user's preferences: Cycles set to render on the GPU renders on the CPU there (no GPU device
  is enabled in factory preferences).
- The process prints one line per view; a thread reads its stdout into a queue that the main
  thread drains: `execute` (scripts, `blender -b`, tests) waits and prints progress; `invoke` (the
  button) returns at once and a modal timer shows progress in the status bar, Esc cancels (the
  process is ended).
- Nothing the user had is lost: the views are rendered into a staging folder beside the
  destination (`.<name>.capturing-<pid>-<random>`); only when every view (and test view) is
  written is it swapped into place (an existing dataset moved aside, the new one renamed in, the
  old one removed). A cancel or a failure removes the staging folder and leaves the destination
  as it was. An existing destination must be empty or a dataset (transforms.json, images/,
  test/ only): a folder holding anything else is refused rather than replaced. Opening another
  file, disabling the add-on or Blender going away ends the renderer the same way (it checks
  after each view that the Blender that started it is still there).
"""

from __future__ import annotations

import collections
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, IntVectorProperty, StringProperty

from ..data.paths import project_folder
from . import dataset as dataset_capture
from .runner import PREFIX

RUNNER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "runner.py")
DATASET_ENTRIES = {"transforms.json", "images", "test"}  # what a destination may hold to be replaced
_live: set[CaptureJob] = set()


class CaptureError(Exception):
    """Bad input or a failed capture, in one line that names the object, folder or value at fault."""


def default_output_folder(scene_name: str) -> str:
    """//nerf_datasets/<scene> beside a saved .blend, else the extension's user folder."""
    name = re.sub(r'[\x00-\x1f/\\:*?"<>|]', "_", scene_name).strip(" .") or "scene"
    return project_folder("nerf_datasets", "datasets", name)


def runner_command(blend: str, config: str) -> list[str]:
    """The command line of the renderer: Blender itself when this is Blender, else this Python
    (the `bpy` module has no Blender binary; bpy.app.binary_path is empty there)."""
    binary = bpy.app.binary_path
    if binary and os.path.isfile(binary) and os.path.basename(binary).lower().startswith("blender"):
        return [binary, "-b", "--factory-startup", blend, "--python-exit-code", "3", "--python", RUNNER, "--", config]
    return [sys.executable, RUNNER, config]


# --------------------------------------------------------------------------- the folders


def _check_destination(dest: str) -> None:
    if os.path.lexists(dest) and not os.path.isdir(dest):
        raise CaptureError(f"output {dest} exists and is not a folder: pick a folder")
    if os.path.isdir(dest):
        try:
            entries = sorted(os.listdir(dest))
        except OSError as exc:
            raise CaptureError(f"cannot read the output folder {dest}: {exc.strerror or exc}") from exc
        foreign = [e for e in entries if e not in DATASET_ENTRIES]
        if foreign:
            shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
            raise CaptureError(
                f"output folder {dest} holds other files than a dataset ({shown}): pick an empty or new folder"
            )


def _make_staging(dest: str) -> str:
    parent, name = os.path.split(os.path.normpath(dest))
    try:
        os.makedirs(parent, exist_ok=True)
    except OSError as exc:
        raise CaptureError(f"cannot create the output's folder {parent}: {exc.strerror or exc}") from exc
    _remove_stale_staging(parent, name)
    try:
        return tempfile.mkdtemp(prefix=f".{name}.capturing-{os.getpid()}-", dir=parent)
    except OSError as exc:
        raise CaptureError(
            f"cannot write in {parent} ({exc.strerror or exc}): pick an output folder you can write to"
        ) from exc


def _remove_stale_staging(parent: str, name: str) -> None:
    """Staging folders of a Blender that died while capturing (POSIX: its pid is gone)."""
    if os.name != "posix":
        return
    pattern = re.compile(rf"^\.{re.escape(name)}\.(capturing|replaced)-(\d+)-")
    try:
        entries = os.listdir(parent)
    except OSError:
        return
    for entry in entries:
        m = pattern.match(entry)
        if not m or int(m.group(2)) == os.getpid():
            continue
        try:
            os.kill(int(m.group(2)), 0)
        except ProcessLookupError:
            shutil.rmtree(os.path.join(parent, entry), ignore_errors=True)
        except OSError:
            pass


def _swap_into_place(staging: str, dest: str) -> None:
    """The new dataset in, the old one (if any) out; the old one stays if the swap fails."""
    if not os.path.lexists(dest):
        os.replace(staging, dest)
        return
    parent, name = os.path.split(os.path.normpath(dest))
    old = tempfile.mkdtemp(prefix=f".{name}.replaced-{os.getpid()}-", dir=parent)
    os.rmdir(old)
    os.replace(dest, old)
    try:
        os.replace(staging, dest)
    except OSError:
        os.replace(old, dest)
        raise
    shutil.rmtree(old, ignore_errors=True)


# --------------------------------------------------------------------------- the background job


@dataclass(eq=False)
class CaptureJob:
    """One capture in its own process: start(), then poll() until it returns True (or wait()),
    or cancel(). `state`: "ready", "running", "done", "failed" or "cancelled"."""

    command: list
    destination: str
    staging: str
    workdir: str
    total: int
    scene: str = ""
    state: str = "ready"
    done: int = 0
    split: str = ""
    error: str = ""
    seconds: float = 0.0
    started: float = 0.0
    _queue: queue.Queue = field(default_factory=queue.Queue, repr=False)
    _tail: collections.deque = field(default_factory=lambda: collections.deque(maxlen=30), repr=False)
    _finished: dict | None = None
    _eof: bool = False

    def start(self) -> None:
        self.started = time.perf_counter()
        try:
            self._proc = subprocess.Popen(
                self.command,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                encoding="utf-8",
                errors="replace",
                bufsize=1,
            )
        except OSError as exc:
            self._cleanup()
            self.state = "failed"
            raise CaptureError(f"cannot start the renderer {self.command[0]}: {exc.strerror or exc}") from exc
        self.state = "running"
        _live.add(self)
        threading.Thread(target=self._read, name="nerf_deform capture reader", daemon=True).start()

    def _read(self) -> None:
        for line in self._proc.stdout:
            self._queue.put(line.rstrip("\n"))
        self._queue.put(None)

    @property
    def fraction(self) -> float:
        return self.done / self.total if self.total else 0.0

    def poll(self) -> bool:
        """Take in what the renderer said; True once the job is over (done, failed or cancelled)."""
        if self.state != "running":
            return self.state != "ready"
        while True:
            try:
                line = self._queue.get_nowait()
            except queue.Empty:
                break
            if line is None:
                self._eof = True
                break
            self._take(line)
        if not self._eof:
            return False
        code = self._proc.wait()
        self.seconds = time.perf_counter() - self.started
        self._end(code)
        return True

    def _take(self, line: str) -> None:
        if not line.startswith(PREFIX):
            if line.strip():
                self._tail.append(line.strip())
            return
        try:
            message = json.loads(line[len(PREFIX) :])
        except ValueError:
            self._tail.append(line)
            return
        if "view" in message:
            self.done, self.split = int(message["view"]), str(message.get("split", ""))
        elif "error" in message:
            self.error = str(message["error"])
        elif message.get("finished"):
            self._finished = message

    def _end(self, code: int) -> None:
        _live.discard(self)
        transforms = os.path.join(self.staging, "transforms.json")
        if code == 0 and self._finished and not self.error and os.path.isfile(transforms):
            try:
                _swap_into_place(self.staging, self.destination)
            except OSError as exc:
                self.error = f"cannot move the new dataset into {self.destination}: {exc.strerror or exc}"
            else:
                self.state = "done"
                self._cleanup()
                return
        if not self.error:
            last = self._tail[-1] if self._tail else "no message"
            self.error = f"the render process ended with exit status {code} before the dataset was complete: {last}"
        self.state = "failed"
        self._cleanup()

    def cancel(self) -> None:
        """End the renderer; the destination stays as it was."""
        if self.state != "running":
            return
        self._proc.terminate()
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        _live.discard(self)
        self.state = "cancelled"
        self.seconds = time.perf_counter() - self.started
        self._cleanup()

    def wait(self, on_progress=None, timeout: float | None = None) -> str:
        """Block until the job is over (calling on_progress(job) as views come); the final state."""
        deadline = None if timeout is None else time.monotonic() + timeout
        seen = -1
        try:
            while not self.poll():
                if self.done != seen and on_progress is not None:
                    seen = self.done
                    on_progress(self)
                if deadline is not None and time.monotonic() > deadline:
                    self.cancel()
                    break
                time.sleep(0.05)
        except BaseException:  # Ctrl-C in `blender -b`: nothing half-made stays behind
            self.cancel()
            raise
        return self.state

    def _cleanup(self) -> None:
        if self.state != "done":
            shutil.rmtree(self.staging, ignore_errors=True)
        shutil.rmtree(self.workdir, ignore_errors=True)


def cancel_all() -> None:
    for job in list(_live):
        job.cancel()


@bpy.app.handlers.persistent
def _cancel_on_load(*_args) -> None:
    """Opening another file ends the captures of this one (their modal operators end with it)."""
    for job in list(_live):
        job.cancel()
        print(f"Capture Dataset: cancelled by loading another file; {job.destination} is as it was", flush=True)


# --------------------------------------------------------------------------- planning


def _options(settings, frame: dict, scene) -> dict:
    min_elevation = float(settings.min_elevation) if settings.use_min_elevation else None
    options = {
        "count": int(settings.count),
        "test_count": int(settings.test_count),
        "resolution": [int(v) for v in settings.resolution],
        "seed": int(settings.seed),
        "radius": float(settings.radius) if settings.radius > 0 else frame["radius"],
        "target": list(frame["target"]),
        "aabb": [list(c) for c in frame["aabb"]],
        "hemisphere": bool(settings.hemisphere) and min_elevation is None,
        "min_elevation": min_elevation,
        "engine": settings.engine,
        "samples": int(settings.samples),
        "opaque": not settings.transparent,
        "lens": float(settings.lens),
        "frame": int(scene.frame_current),
        "extras": {
            "tool": "Capture Dataset (blender_nerf_deform)",
            "scene": scene.name,
            "selection": frame["names"],
            "selection_bounds": [list(c) for c in frame["bounds"]],
        },
    }
    opts = dataset_capture.Options(
        **{k: tuple(v) if k in ("resolution", "target") else v for k, v in options.items() if k != "aabb"},
        aabb=tuple(map(tuple, options["aabb"])),
    )
    try:
        opts.validate()
    except dataset_capture.DatasetError as exc:  # named as the panel names them, not as options
        raise CaptureError(re.sub(r"--([a-z-]+)", lambda m: m.group(1).replace("-", " "), str(exc))) from exc
    return options


def start_capture(context, settings) -> CaptureJob:
    """Check the input, save the copy, start the renderer: the running job. `settings` has the
    Capture Dataset properties (the operator, or the scene's `nerf_deform_capture`). Raises
    CaptureError with a one-line message."""
    scene = context.scene
    selected = list(context.selected_objects)
    if not selected:
        raise CaptureError("no objects selected: select the objects to capture (the cameras look at them)")
    objects = dataset_capture.renderable(selected)
    if not objects:
        kinds = ", ".join(sorted({o.type.lower() for o in selected}))
        raise CaptureError(
            f"none of the selected objects renders (selected: {kinds}): select a mesh, curve, text, "
            f"volume or point cloud that is not hidden from render"
        )
    if settings.engine == "KEEP" and scene.render.engine not in dataset_capture.BUILTIN_ENGINES:
        raise CaptureError(
            f"the scene's render engine {scene.render.engine!r} comes from an add-on, which the "
            f"background Blender does not load: set Engine to Cycles"
        )
    try:
        frame = dataset_capture.selection_frame(bpy, objects, tuple(settings.resolution), float(settings.lens))
    except dataset_capture.DatasetError as exc:
        raise CaptureError(str(exc)) from exc
    frame["names"] = [o.name for o in objects]
    options = _options(settings, frame, scene)

    dest = os.path.abspath(bpy.path.abspath(settings.output)) if settings.output else default_output_folder(scene.name)
    for job in _live:
        if os.path.normpath(job.destination) == os.path.normpath(dest):
            raise CaptureError(f"a capture into {dest} is already running: wait for it or cancel it")
    _check_destination(dest)
    staging = _make_staging(dest)
    workdir = tempfile.mkdtemp(prefix="nerf_deform_capture_")
    try:
        blend = os.path.join(workdir, "scene.blend")
        if bpy.ops.wm.save_as_mainfile(filepath=blend, copy=True, check_existing=False) != {
            "FINISHED"
        } or not os.path.isfile(blend):
            raise CaptureError(f"Blender could not save a copy of the scene to {blend}")
        keep = {o.name for o in objects}
        hide = [
            o.name
            for o in scene.objects
            if settings.selected_only and o.name not in keep and o.type in dataset_capture.RENDERABLE_TYPES
        ]
        config = os.path.join(workdir, "capture.json")
        with open(config, "w", encoding="utf-8") as f:
            json.dump(
                {
                    "blend": blend,
                    "scene": scene.name,
                    "out": staging,
                    "hide": hide,
                    "parent_pid": os.getpid(),
                    "options": options,
                },
                f,
            )
    except (OSError, RuntimeError, CaptureError) as exc:
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(workdir, ignore_errors=True)
        if isinstance(exc, CaptureError):
            raise
        raise CaptureError(f"cannot save a copy of the scene for the renderer: {exc}") from exc
    job = CaptureJob(
        runner_command(blend, config),
        dest,
        staging,
        workdir,
        total=int(settings.count) + int(settings.test_count),
        scene=scene.name,
    )
    job.start()
    return job


def finish(job: CaptureJob) -> str:
    """After a successful capture: the Train panel's Dataset field shows it; the one-line summary."""
    scene = bpy.data.scenes.get(job.scene)
    if scene is not None and hasattr(scene, "nerf_deform_training"):
        scene.nerf_deform_training.data = job.destination  # absolute: the field takes no // paths
    return f"{job.total} views in {job.seconds:.1f} s -> {job.destination} (the Train panel's Dataset)"


# --------------------------------------------------------------------------- operator, settings, panel


class _CaptureProperties:
    """The settings of a capture, shared by the operator and the scene's panel settings."""

    output: StringProperty(
        name="Output Folder",
        subtype="DIR_PATH",
        description="Folder of the dataset (empty: //nerf_datasets/<scene name> beside the saved "
        ".blend, else the extension's user folder). An existing dataset there is "
        "replaced once the new one is complete",
    )
    count: IntProperty(name="Views", default=100, min=1, max=10000, description="Training views")
    test_count: IntProperty(
        name="Test Views",
        default=0,
        min=0,
        max=10000,
        description="Other random views written to test/ (for PSNR on held-out views)",
    )
    radius: FloatProperty(
        name="Radius",
        default=0.0,
        min=0.0,
        subtype="DISTANCE",
        unit="LENGTH",
        description="Distance of the cameras from the centre of the selection "
        "(0: automatic, the selection fills the picture)",
    )
    resolution: IntVectorProperty(
        name="Resolution",
        size=2,
        default=(200, 200),
        min=8,
        max=16384,
        description="Width and height of the views in pixels",
    )
    lens: FloatProperty(
        name="Focal Length",
        default=50.0,
        min=1.0,
        max=5000.0,
        subtype="DISTANCE_CAMERA",
        description="Focal length of the cameras in mm (36 mm sensor)",
    )
    seed: IntProperty(name="Seed", default=0, min=0, description="Seed of the camera layout (and of Cycles)")
    hemisphere: BoolProperty(name="Hemisphere", default=False, description="Cameras on the upper (+Z) half only")
    use_min_elevation: BoolProperty(
        name="Minimum Elevation", default=False, description="Cameras only above an elevation (replaces Hemisphere)"
    )
    min_elevation: FloatProperty(
        name="Elevation",
        default=-15.0,
        min=-90.0,
        max=89.0,
        description="Lowest camera elevation in degrees above the selection's centre",
    )
    engine: EnumProperty(
        name="Engine",
        default="KEEP",
        items=(
            ("KEEP", "Scene's Engine", "The scene's render engine and its sampling settings"),
            ("CYCLES", "Cycles (CPU)", "Cycles on the CPU with the samples below, deterministic"),
        ),
    )
    samples: IntProperty(name="Samples", default=16, min=1, max=1 << 16, description="Cycles samples (Engine: Cycles)")
    transparent: BoolProperty(
        name="Transparent",
        default=True,
        description="Transparent film: RGBA with straight alpha. Off: opaque RGB views with "
        "the background (a room, the world) in them",
    )
    selected_only: BoolProperty(
        name="Selected Only",
        default=True,
        description="Render only the selected objects (the others are hidden in the "
        "capture; lights and the world still light them)",
    )


CAPTURE_OPTIONS = (
    "output",
    "count",
    "test_count",
    "radius",
    "resolution",
    "lens",
    "seed",
    "hemisphere",
    "use_min_elevation",
    "min_elevation",
    "engine",
    "samples",
    "transparent",
    "selected_only",
)


class NERFDEFORM_OT_capture_dataset(_CaptureProperties, bpy.types.Operator):
    """Render a NeRF dataset of the selected objects (cameras around them, the scene's render engine) in the background; Esc cancels"""  # noqa: E501 (the tooltip: one line)

    bl_idname = "nerf_deform.capture_dataset"
    bl_label = "Capture Dataset"
    bl_options = {"REGISTER"}

    _job: CaptureJob | None = None
    _timer = None

    def _fail(self, message: str) -> set[str]:
        self.report({"ERROR"}, f"{self.bl_label}: {message}")
        return {"CANCELLED"}

    def _over(self, job: CaptureJob) -> set[str]:
        if job.state == "done":
            self.report({"INFO"}, f"{self.bl_label}: {finish(job)}")
            return {"FINISHED"}
        if job.state == "cancelled":
            self.report({"WARNING"}, f"{self.bl_label}: cancelled; {job.destination} is as it was")
            return {"CANCELLED"}
        return self._fail(job.error)

    def execute(self, context):
        try:
            job = start_capture(context, self)
        except CaptureError as error:
            return self._fail(str(error))
        job.wait(on_progress=lambda j: print(f"{self.bl_label}: {j.done}/{j.total} views", flush=True))
        return self._over(job)

    def invoke(self, context, event):
        try:
            self._job = start_capture(context, self)
        except CaptureError as error:
            return self._fail(str(error))
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC":
            job.cancel()
        elif event.type != "TIMER":
            return {"PASS_THROUGH"}
        if not job.poll():
            context.window_manager.progress_update(int(100 * job.fraction))
            context.workspace.status_text_set(
                f"{self.bl_label}: {job.done}/{job.total} views ({100 * job.fraction:.0f}%) (Esc to cancel)"
            )
            return {"RUNNING_MODAL"}
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        context.workspace.status_text_set(None)
        return self._over(job)


class NERFDEFORM_CaptureSettings(_CaptureProperties, bpy.types.PropertyGroup):
    """The Capture Dataset panel's fields (the scene's), handed to the operator when its button is pressed."""


_classes = (NERFDEFORM_OT_capture_dataset, NERFDEFORM_CaptureSettings)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(_classes)


def register():
    _register_classes()
    bpy.types.Scene.nerf_deform_capture = bpy.props.PointerProperty(type=NERFDEFORM_CaptureSettings)
    bpy.app.handlers.load_pre.append(_cancel_on_load)


def unregister():
    cancel_all()
    if _cancel_on_load in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_cancel_on_load)
    del bpy.types.Scene.nerf_deform_capture
    _unregister_classes()
