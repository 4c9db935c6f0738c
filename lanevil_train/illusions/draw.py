"""Drawing in world space: project road-frame and 3D shapes into the image, fill, shade, blend.

Shapes are projected vertex by vertex (after densifying their edges, so a polygon laid on a
curved or sloped road bends with it) and filled with OpenCV in image space: a planar polygon
maps to the image exactly, and filling is far cheaper than inverse-projecting every pixel.
`RoadLight`, `in_view` and `visible_side` help illusions land where the camera can see them (in
view, and at night in the light), so that even level 1 is visible (issue 10).
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


def in_front(ctx: IllusionContext, points: np.ndarray, near: float = NEAR_Z) -> np.ndarray:
    """Boolean (...,): world points more than `near` metres ahead of the camera (their forward
    distance z; in a clip frame, z in the moved camera's world)."""
    pts = np.asarray(points, dtype=np.float64)
    if ctx.view is not None:
        pts = ctx.view.to_current(pts)
    return pts[..., 2] > near


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


def project_ground_polygon(ctx: IllusionContext, poly_dz: np.ndarray, step: float = 0.5) -> np.ndarray | None:
    """Pixel outline (K, 2) of a road-frame polygon (d, z), or None when nothing of it is in front.

    Edges are densified every `step` metres. The polygon is clipped to z >= NEAR_Z, and further
    forward while any of its points is still behind the camera plane (a yawed camera sees the road
    edges only from some distance on), so no vertex ever projects from behind the camera.
    """
    poly = np.asarray(poly_dz, dtype=np.float64)
    z_min = NEAR_Z
    for _ in range(6):
        clipped = clip_near(poly, z_min)
        if len(clipped) < 3:
            return None
        dense = densify(clipped, step)
        pix, depth = project(ctx, road_points(ctx, dense[:, 0], dense[:, 1]))
        bad = ~(depth > 0.5 * NEAR_Z) | ~np.all(np.isfinite(pix), axis=1)
        if not bad.any():
            return pix
        z_min = float(dense[bad, 1].max()) + step
    return None


def ground_polygon_mask(ctx: IllusionContext, polygons_dz: list[np.ndarray], step: float = 0.5,
                        mask: np.ndarray | None = None) -> np.ndarray:
    """Fill polygons given in road coordinates (each (K, 2) of (d, z)) into an image mask.

    Edges are densified every `step` metres; what lies behind the camera is clipped away
    (`project_ground_polygon`).
    """
    projected = [project_ground_polygon(ctx, poly, step) for poly in polygons_dz]
    return fill_polygons(ctx.image_size, [pix for pix in projected if pix is not None], mask=mask)


def soften(mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian-blur a mask (penumbra, worn edges); sigma 0 returns it unchanged."""
    if sigma_px <= 0:
        return mask
    return cv2.GaussianBlur(mask, (0, 0), sigmaX=float(sigma_px))


def shade(image: np.ndarray, mask: np.ndarray, factor) -> np.ndarray:
    """Multiply the image by `factor` (scalar or RGB) where mask is 1, blending by mask in between.

    factor < 1 darkens (shadows), > 1 brightens (glare); the result is clipped to uint8.
    Only the mask's bounding box is computed: outside it the factor is 1 and the image is returned as it is (the
    same bytes as computing it everywhere: uint8 * 1.0 + 0.5 truncates back to itself), a few ms a frame less.
    """
    f = np.asarray(factor, dtype=np.float32).reshape(1, 1, -1)
    whole = image.dtype != np.uint8  # a float image is rounded everywhere
    box = (slice(None), slice(None)) if whole else nonzero_box(mask)
    out = np.empty(image.shape, np.uint8) if whole else image.copy()
    if box is None:
        return out
    m = mask[box][..., None].astype(np.float32)
    shaded = image[box].astype(np.float32) * (1.0 + m * (f - 1.0))
    out[box] = np.clip(shaded + 0.5, 0, 255).astype(np.uint8)
    return out


def nonzero_box(mask: np.ndarray) -> tuple[slice, slice] | None:
    """(rows, columns) slices of the smallest box holding every non-zero pixel of a 2-D mask; None when all are 0."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask[rows[0]:rows[-1] + 1].any(axis=0))
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def overlay(image: np.ndarray, mask: np.ndarray, color, alpha: float = 1.0) -> np.ndarray:
    """Blend the image towards an RGB colour (0..255) by mask * alpha (paint, tar, occluders)."""
    m = (mask.astype(np.float32) * float(alpha))[..., None]
    c = np.asarray(color, dtype=np.float32).reshape(1, 1, 3)
    out = image.astype(np.float32) * (1.0 - m) + c * m
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def road_mask(ctx: IllusionContext, far: float = 150.0, margin: float = 0.0) -> np.ndarray:
    """Mask of the asphalt between the road's left and right edges (grown by `margin` metres on
    each side, e.g. to take in the verge), out to `far` metres.

    The band starts at the nearest distance where both edges are in front of the camera, so a
    strongly turned (yawed) camera still gets its road.
    """
    zs = np.linspace(NEAR_Z, far, 96)
    sides = (ctx.road.left_edge - margin, ctx.road.right_edge + margin)
    edges = [road_points(ctx, np.full_like(zs, d), zs) for d in sides]
    (pl, dl), (pr, dr) = (project(ctx, e) for e in edges)
    ok = (dl > NEAR_Z) & (dr > NEAR_Z) & np.all(np.isfinite(pl), 1) & np.all(np.isfinite(pr), 1)
    if ok.sum() < 2:
        return np.zeros(ctx.image_size, np.float32)
    return fill_polygons(ctx.image_size, [np.concatenate([pl[ok], pr[ok][::-1]])])


LIT_SUM = 150.0  # RGB sum (0..765) from which a subtle darkening of the road shows (50 per channel)
DARK_SUM = 60.0  # ground whose darkest tenth is below this RGB sum is dark (night: unlit stretches)


class RoadLight:
    """How bright the image is around road points: lets an illusion land where it can be seen.

    The image is shrunk 5x once (an area average); `at(d, z)` reads the RGB sum (0..765) there, -1
    for points behind the camera or off the image; `pick(d, z)` chooses among candidate places.
    """

    def __init__(self, image: np.ndarray, ctx: IllusionContext, cell: int = 5):
        if ctx.view is not None:  # a clip frame: read the reference view, so every frame picks the same
            image = image if ctx.placement_image is None else ctx.placement_image
            ctx = ctx.placement
        h, w = ctx.image_size
        self.ctx = ctx
        self.scale = (max(1, w // cell) / w, max(1, h // cell) / h)
        self.small = cv2.resize(image, (max(1, w // cell), max(1, h // cell)),
                                interpolation=cv2.INTER_AREA).astype(np.float32).sum(axis=2)
        self._dark: bool | None = None

    def at(self, d, z, lift=0.0) -> np.ndarray:
        """RGB sum of the image at road points (d, z) (`lift` metres up), -1 where not in view."""
        d, z = np.broadcast_arrays(np.asarray(d, np.float64), np.asarray(z, np.float64))
        pix, depth = project(self.ctx, road_points(self.ctx, d.ravel(), z.ravel(), lift))
        sh, sw = self.small.shape
        u, v = pix[:, 0] * self.scale[0], pix[:, 1] * self.scale[1]
        ok = (depth > NEAR_Z) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < sw) & (v >= 0) & (v < sh)
        out = np.full(d.size, -1.0)
        out[ok] = self.small[v[ok].astype(int), u[ok].astype(int)]
        return out.reshape(d.shape)

    def road_is_dark(self) -> bool:
        """Whether the ground ahead (asphalt and 1 m of verge, 4-40 m) has unlit stretches: night."""
        road = self.ctx.road
        d = np.linspace(road.left_edge - 1.0, road.right_edge + 1.0, 11)
        light = self.at(*np.meshgrid(d, np.geomspace(4.0, 40.0, 9)))
        light = light[light >= 0]
        return bool(np.percentile(light, 10) < DARK_SUM) if len(light) else False

    def pick(self, d, z) -> int:
        """Index of the first candidate place (d[i], z[i]) in view and lit well enough to show a
        darkening: at least LIT_SUM bright, or 60 % as bright as the brightest candidate (80 % on a
        dark road, where the light is a small pool). By day that is the first candidate in view (the
        plain random placement); at night one in the light."""
        light = self.at(d, z)
        top = float(light.max())
        if top < 0:
            return 0
        if self._dark is None:
            self._dark = self.road_is_dark()
        threshold = 0.8 * top if self._dark else min(LIT_SUM, 0.6 * top)
        return int(np.flatnonzero(light >= threshold)[0])


def row_distance(ctx: IllusionContext) -> np.ndarray:
    """Forward distance (m) of the road seen on each image row (H,), along the centre column; inf
    above the horizon. Enough for effects that fade with distance, such as a lamp's reach."""
    ctx = ctx.frame()  # a clip frame: distances from the moved camera
    h, w = ctx.image_size
    v = np.arange(h, dtype=np.float64)
    z = ctx.camera.ground_intersect(np.full(h, ctx.camera.cx), v, surface=ctx.road)[:, 2]
    return np.where(np.isfinite(z) & (z > 0), z, np.inf)


def in_view(ctx: IllusionContext, d: float, zs: tuple[float, ...] = (8.0, 12.0)) -> bool:
    """Whether the road line at lateral offset d shows in the image at any of these distances (in the
    reference view of a clip frame: a placement decision, the same for every frame)."""
    ctx = ctx.placement
    h, w = ctx.image_size
    pix, depth = project(ctx, road_points(ctx, np.full(len(zs), float(d)), np.asarray(zs, np.float64)))
    ok = (depth > NEAR_Z) & np.all(np.isfinite(pix), axis=1)
    return bool(np.any(ok & (pix[:, 0] >= 0) & (pix[:, 0] < w) & (pix[:, 1] >= 0) & (pix[:, 1] < h)))


def visible_side(ctx: IllusionContext, first: int, d_of_side) -> int:
    """`first` (+1 right / -1 left, drawn by the caller), unless only the other side's roadside line
    `d_of_side(side)` is in view: an object beside the road stands where the camera can see it."""
    if in_view(ctx, d_of_side(first)) or not in_view(ctx, d_of_side(-first)):
        return first
    return -first
