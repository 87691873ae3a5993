"""Deform stage: handles and pins, the cage's pose for a frame (worker requests), the live preview."""
