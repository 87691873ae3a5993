"""Samples per step of a frame's march: what `render`, `eval`, the worker and the add-on's render settings
share (torch-free, so the command line's `--help` and Blender's add-on can read it).

The NeRF trains on jittered samples one render step apart (`NerfConfig.render_step`), which averages its
colour over each step; a frame marched at a fraction of that step is a finer quadrature of the field it
learnt. On held-out photos half the step is a measurable gain for less than twice the frame's time; a
third of it adds little for more time.
Final frames (`render`, `eval`, F12, batch renders, the last image of the viewport) take FINAL_SUBSTEPS;
the viewport's coarse images and training previews 1.
"""

from __future__ import annotations

from ..errors import EngineError

FINAL_SUBSTEPS = 2
MAX_SUBSTEPS = 16


def check_substeps(value) -> int:
    """`value` as a number of substeps, or EngineError naming what is wrong."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_SUBSTEPS:
        raise EngineError(
            f"substeps = {value!r} is invalid: it must be an integer from 1 to {MAX_SUBSTEPS} "
            "(samples per step of the NeRF's march)"
        )
    return value
