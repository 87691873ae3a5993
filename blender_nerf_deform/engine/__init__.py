"""The engine: training, extraction, cage, deformation and ray-bent rendering.

Never imports bpy. Runs in plain Python: the command line, the tests and the
worker process that the Blender add-on talks to. One package per pipeline
stage (nerf/, geometry/, bend/), the plumbing apart (cli/: one module per
command; service/: the worker), and backend.py, which decides once whether
CPU work runs numba's kernels or torch. Importing this package imports
nothing heavy.
"""
