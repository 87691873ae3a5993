"""The engine: training, extraction, cage, deformation and ray-bent rendering.

Never imports bpy. Runs in plain Python: the command line, the tests and the
worker process that the Blender add-on talks to.
"""
