"""Several NeRFs in one image: each rendered on its own, then merged per pixel, front to back.

Every NeRF object is rendered by the worker as a separate request (its own
checkpoint, cage and pose), giving per pixel a premultiplied colour C_k, an
alpha a_k and an expected depth z_k (planar, world units). The image is their
"over" composite in the order of z_k at that pixel, front first:

    C = C_0 + (1 - a_0) C_1 + (1 - a_0)(1 - a_1) C_2 + ...,   A likewise.

Where this is exact: the volume-rendering integral along a ray splits at any
point into the part before it plus the transmittance times the part after it.
So when the NeRFs' contents occupy disjoint stretches of the ray (they do not
overlap in the image, or one lies wholly in front of the other there, which
includes boxes that overlap in space while their contents do not), "over" in
depth order gives exactly what one march through all of them would. Where it
approximates: volumes that interpenetrate along a ray (a NeRF reaching through
another, two hazes mixed); each is then treated as a layer at its expected
depth, so the one whose mass lies mostly in front hides the other's samples
that are really in front of part of it.

Why not merge the samples (march every NeRF along the same ray and sort the
samples): the engine renders one NeRF per request, with that NeRF's own
occupancy grid, bend and sample spacing; a sample-level merge would need one
engine render interleaving several models per ray (memory and work for all of
them at every step) for a case, interpenetrating volumes, that scenes of
separate objects rarely have. Per-NeRF renders keep each request as it is (a
single NeRF renders exactly as before, bit for bit), let the worker keep each
NeRF's cached state, and make progress and Esc work per NeRF.

The Depth pass is the depth of the front-most NeRF that covers the pixel,
"covers" meaning alpha > COVERS_ALPHA, so a faint haze of one NeRF in front of
another's solid surface does not claim the pixel (Z Combine with the scene's
meshes then keeps the surface's depth). Where no NeRF covers a pixel that much
(edges, thin haze) the front-most one with any coverage gives it, as a single
NeRF's Depth pass does; NO_HIT_DEPTH where nothing is there (Cycles'
convention).
"""

from __future__ import annotations

import numpy as np

NO_HIT_DEPTH = 1e10
HIT_ALPHA = 1e-6  # any coverage at all: the pixel has a depth
COVERS_ALPHA = 0.5  # coverage that claims the Depth pass from NeRFs behind


def composite_by_depth(layers: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """[(premultiplied RGBA (H,W,4), planar depth (H,W), NO_HIT_DEPTH where empty), ...] → (RGBA, depth)."""
    if len(layers) == 1:
        rgba, depth = layers[0]
        return rgba, depth
    rgba = np.stack([np.asarray(c, dtype=np.float32) for c, _ in layers])  # (N,H,W,4)
    depth = np.stack([np.asarray(z, dtype=np.float32) for _, z in layers])  # (N,H,W)
    alpha = rgba[..., 3]
    # Uncovered layers sort last, whatever depth they carry.
    key = np.where(alpha > HIT_ALPHA, depth, np.inf)
    order = np.argsort(key, axis=0, kind="stable")  # stable: ties keep the NeRFs' (name) order
    rgba = np.take_along_axis(rgba, order[..., None], axis=0)
    depth = np.take_along_axis(depth, order, axis=0)
    alpha = rgba[..., 3]

    out = np.zeros(rgba.shape[1:], dtype=np.float32)
    transmittance = np.ones(alpha.shape[1:], dtype=np.float32)
    for k in range(len(layers)):
        out += transmittance[..., None] * rgba[k]
        transmittance *= 1.0 - alpha[k]

    # Front-most covering layer, else the front-most with any coverage, else nothing.
    covers = alpha > COVERS_ALPHA
    hit = alpha > HIT_ALPHA
    first_cover = np.argmax(covers, axis=0)
    first_hit = np.argmax(hit, axis=0)
    chosen = np.where(covers.any(axis=0), first_cover, first_hit)
    front_depth = np.take_along_axis(depth, chosen[None], axis=0)[0]
    front_depth = np.where(hit.any(axis=0), front_depth, NO_HIT_DEPTH).astype(np.float32)
    return out, front_depth
