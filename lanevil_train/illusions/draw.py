"""Drawing in world space: project road-frame and 3D shapes into the image, fill, shade, blend.

Shapes are projected vertex by vertex (after densifying their edges, so a polygon laid on a
curved or sloped road bends with it) and filled with OpenCV in image space: a planar polygon
maps to the image exactly, and filling is far cheaper than inverse-projecting every pixel.
"""

from __future__ import annotations

import cv2
import numpy as np

from lanevil_train.illusions.context import IllusionContext

NEAR_Z = 0.5  # metres: geometry closer than this to the camera plane is clipped away

_SHIFT = 4  # cv2 fixed-point bits: sub-pixel vertex positions for smooth edges


def densify(polygon: np.ndarray, step: float) -> np.ndarray:
    """Insert points along each edge of a closed polygon (K, C) so no edge is longer than `step`."""
    pts = np.asarray(polygon, dtype=np.float64)
    out = []
    for a, b in zip(pts, np.roll(pts, -1, axis=0)):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * (np.arange(n)[:, None] / n))
    return np.concatenate(out)


def road_points(ctx: IllusionContext, d, z, lift=0.0) -> np.ndarray:
    """World points (..., 3) at road offset d, forward distance z, `lift` metres above the surface."""
    pts = ctx.road.world_point(d, z)
    return pts + np.array([0.0, 1.0, 0.0]) * np.asarray(lift, dtype=np.float64)[..., None]


def project(ctx: IllusionContext, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (..., 3) -> pixels (..., 2) and camera depth (...,)."""
    return ctx.camera.project(points, return_depth=True)


def fill_polygons(shape: tuple[int, int], polygons_px: list[np.ndarray], value: float = 1.0,
                  mask: np.ndarray | None = None) -> np.ndarray:
    """Fill pixel polygons (each (K, 2)) into a float32 mask of `shape` (anti-aliased edges)."""
    mask = np.zeros(shape, np.float32) if mask is None else mask
    for p in polygons_px:
        if len(p) >= 3 and np.all(np.isfinite(p)):
            # one call per polygon: given several at once, cv2 leaves holes where they overlap
            pts = np.round(np.asarray(p) * (1 << _SHIFT)).astype(np.int32)
            cv2.fillPoly(mask, [pts], float(value), lineType=cv2.LINE_AA, shift=_SHIFT)
    return mask


def clip_near(poly: np.ndarray, z_min: float = NEAR_Z) -> np.ndarray:
    """Clip a road-frame polygon (K, 2) of (d, z) to z >= z_min (Sutherland-Hodgman, one plane)."""
    out = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        a_in, b_in = a[1] >= z_min, b[1] >= z_min
        if a_in:
            out.append(a)
        if a_in != b_in:
            out.append(a + (b - a) * ((z_min - a[1]) / (b[1] - a[1])))
    return np.array(out).reshape(-1, 2)


def ground_polygon_mask(ctx: IllusionContext, polygons_dz: list[np.ndarray], step: float = 0.5,
                        mask: np.ndarray | None = None) -> np.ndarray:
    """Fill polygons given in road coordinates (each (K, 2) of (d, z)) into an image mask.

    Edges are densified every `step` metres and the part nearer than NEAR_Z is clipped away.
    """
    h, w = ctx.image_size
    projected = []
    for poly in polygons_dz:
        poly = clip_near(np.asarray(poly, dtype=np.float64))
        if len(poly) < 3:
            continue
        dense = densify(poly, step)
        pix, depth = project(ctx, road_points(ctx, dense[:, 0], dense[:, 1]))
        if np.all(depth > 0) and np.all(np.isfinite(pix)):
            projected.append(pix)
    return fill_polygons((h, w), projected, mask=mask)


def soften(mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian-blur a mask (penumbra, worn edges); sigma 0 returns it unchanged."""
    if sigma_px <= 0:
        return mask
    return cv2.GaussianBlur(mask, (0, 0), sigmaX=float(sigma_px))


def shade(image: np.ndarray, mask: np.ndarray, factor) -> np.ndarray:
    """Multiply the image by `factor` (scalar or RGB) where mask is 1, blending by mask in between.

    factor < 1 darkens (shadows), > 1 brightens (glare); the result is clipped to uint8.
    """
    f = np.asarray(factor, dtype=np.float32).reshape(1, 1, -1)
    m = mask[..., None].astype(np.float32)
    out = image.astype(np.float32) * (1.0 + m * (f - 1.0))
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def overlay(image: np.ndarray, mask: np.ndarray, color, alpha: float = 1.0) -> np.ndarray:
    """Blend the image towards an RGB colour (0..255) by mask * alpha (paint, tar, occluders)."""
    m = (mask.astype(np.float32) * float(alpha))[..., None]
    c = np.asarray(color, dtype=np.float32).reshape(1, 1, 3)
    out = image.astype(np.float32) * (1.0 - m) + c * m
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def road_mask(ctx: IllusionContext, far: float = 150.0) -> np.ndarray:
    """Mask of the asphalt between the road's left and right edges, out to `far` metres.

    The band starts at the nearest distance where both edges are in front of the camera, so a
    strongly turned (yawed) camera still gets its road.
    """
    zs = np.linspace(NEAR_Z, far, 96)
    edges = [road_points(ctx, np.full_like(zs, d), zs) for d in (ctx.road.left_edge, ctx.road.right_edge)]
    (pl, dl), (pr, dr) = (project(ctx, e) for e in edges)
    ok = (dl > NEAR_Z) & (dr > NEAR_Z) & np.all(np.isfinite(pl), 1) & np.all(np.isfinite(pr), 1)
    if ok.sum() < 2:
        return np.zeros(ctx.image_size, np.float32)
    return fill_polygons(ctx.image_size, [np.concatenate([pl[ok], pr[ok][::-1]])])
