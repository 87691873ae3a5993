"""Capture Dataset's background process: render a dataset from a saved copy of the user's file.

capture/operators.py starts it, never a user:

    blender -b --factory-startup COPY.blend --python-exit-code 3 --python runner.py -- CONFIG.json
    PYTHON runner.py CONFIG.json        (the bpy module: a Python that imports bpy, no Blender binary)

CONFIG.json: {"blend": COPY.blend, "scene": name, "out": the staging folder, "hide": [names of
objects to hide from render], "parent_pid": pid of the Blender that started it, "options": the
keyword options of capture/dataset.py's make_dataset}.

It prints one machine-readable line per rendered view on stdout, and one at the end:

    NERF_DEFORM_CAPTURE {"view": 3, "total": 12, "split": "train", "seconds": 0.21}
    NERF_DEFORM_CAPTURE {"finished": true, "transforms": ".../transforms.json", "seconds": 4.2}
    NERF_DEFORM_CAPTURE {"error": "one line naming what failed"}      (then exit status 2)

Everything else on stdout/stderr is Blender's own talk, which the add-on keeps only to explain
a crash. The process ends itself when the Blender that started it is gone.

It loads `capture/dataset.py` (and, through its relative imports, `data/camera.py`) from the
add-on's folder as the submodules of a private package, so it works wherever the add-on lives
(`blender_nerf_deform.addon`, or `bl_ext.<repo>.blender_nerf_deform.addon` as an extension)
without running the add-on's `__init__` (nothing is registered in this Blender).
"""

import importlib
import json
import os
import sys
import traceback
import types

PREFIX = "NERF_DEFORM_CAPTURE "
_PACKAGE = "_nerf_deform_capture"


def _say(**message) -> None:
    sys.stdout.write(PREFIX + json.dumps(message) + "\n")
    sys.stdout.flush()


def load_capture_module():
    """capture/dataset.py of the add-on folder above this file's, as `_nerf_deform_capture.capture.dataset`
    (the sub-packages' __init__ files hold docstrings only, so nothing else runs)."""
    if _PACKAGE not in sys.modules:
        package = types.ModuleType(_PACKAGE)
        package.__path__ = [os.path.dirname(os.path.dirname(os.path.abspath(__file__)))]
        package.__package__ = _PACKAGE
        sys.modules[_PACKAGE] = package
    return importlib.import_module(f"{_PACKAGE}.capture.dataset")


def _config_path(argv) -> str:
    args = argv[argv.index("--") + 1 :] if "--" in argv else argv[1:]
    if len(args) != 1:
        raise SystemExit(f"usage: runner.py CONFIG.json (got {args!r})")
    return args[0]


def run(config: dict) -> int:
    capture = load_capture_module()
    import bpy  # noqa: PLC0415

    blend = config["blend"]
    loaded = bpy.data.filepath
    if not (loaded and os.path.exists(loaded) and os.path.samefile(loaded, blend)):
        bpy.ops.wm.open_mainfile(filepath=blend, load_ui=False)
    scene = bpy.data.scenes.get(config["scene"])
    if scene is None:
        raise capture.DatasetError(f"the saved copy has no scene {config['scene']!r}")
    window = bpy.context.window
    if window is not None and window.scene != scene:
        window.scene = scene
    for name in config.get("hide", ()):
        obj = bpy.data.objects.get(name)
        if obj is not None:
            obj.hide_render = True

    parent = config.get("parent_pid")

    def on_view(done, total, split, path, seconds):
        if parent is not None and os.getppid() != parent:  # the Blender that asked is gone
            os._exit(4)
        _say(view=done, total=total, split=split, seconds=round(seconds, 4))

    options = dict(config["options"])
    if "resolution" in options:
        options["resolution"] = tuple(options["resolution"])
    for key in ("target", "shift"):
        if key in options:
            options[key] = tuple(options[key])
    if options.get("aabb") is not None:
        options["aabb"] = tuple(tuple(c) for c in options["aabb"])
    result = capture.make_dataset(config["out"], blend=None, progress=None, quiet=True, on_view=on_view, **options)
    _say(finished=True, transforms=str(result["transforms"]), seconds=round(result["seconds"], 3))
    return 0


def main(argv=None) -> int:
    argv = sys.argv if argv is None else argv
    try:
        with open(_config_path(argv), encoding="utf-8") as f:
            config = json.load(f)
        return run(config)
    except Exception as exc:  # noqa: BLE001  (reported to the add-on in one line; the trace for a crash report)
        capture = sys.modules.get(f"{_PACKAGE}.capture.dataset")
        if capture is not None and isinstance(exc, capture.DatasetError):
            _say(error=str(exc))
        else:
            traceback.print_exc()
            lines = [line for line in str(exc).strip().splitlines() if line.strip()]
            _say(error=f"{type(exc).__name__}: {lines[-1] if lines else 'no message'}")
        return 2


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    if code:
        sys.exit(code)
