"""Render stage: a frame's worker requests and passes, the NeRF Deform render engine (F12, `-a`), the
viewport's Rendered shading, Preview Render, Composite With Scene."""
