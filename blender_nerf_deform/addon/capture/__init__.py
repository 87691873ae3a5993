"""Capture stage: Capture Dataset renders a NeRF dataset of the scene (the operator, the shared capture
core, and the background process that runs it). Docstring only: capture/runner.py imports
capture.dataset as part of a private package."""
