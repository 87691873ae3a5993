"""The worker process Blender talks to: wire protocol, op registry, the ops (thin calls of the
stage functions) and the worker session that keeps what Blender sent under content keys."""
