"""Road geometry in world metres: centre line x_c(z), height h(z), lane boundaries and their paint.

The road is described as functions of the forward distance z (world frame of camera.py):
  x_c(z) = x0 + k z^2 / 2 + j z^3 / 6        (curvature k + j z: curves and S-curves)
  h(z)   = 0 before z_b, a parabolic vertical curve of length L, then a constant grade g.
Road coordinates of a ground point (x, z) are s (arc length of the centre line up to z) and
d (signed lateral distance from the centre line, perpendicular to it to first order, + right).
Every function is vectorised over numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Z_MAX = 2000.0  # rays hitting the ground beyond this are treated as misses (haze/horizon)


@dataclass(frozen=True)
class Stripe:
    """One painted stripe of a marking: lateral offset from the marking centre, width, dashed?"""

    offset: float
    width: float
    dashed: bool
    dots: bool = False


@dataclass(frozen=True)
class Boundary:
    """A lane boundary at road offset d (metres) with its marking type and stripes."""

    d: float
    marking: str
    stripes: tuple[Stripe, ...]
    color: str  # "white" | "yellow" | "none"


@dataclass(frozen=True)
class RoadGeometry:
    """Centre line, vertical profile and lane layout of one road (world metres)."""

    x0: float = 0.0  # centre-line x at z = 0 (camera is at x = 0)
    k: float = 0.0  # curvature at z = 0 (1/m, + bends right)
    j: float = 0.0  # curvature change per metre (1/m^2)
    grade: float = 0.0  # final slope dh/dz (+ uphill)
    slope_start: float = 25.0  # z where the vertical curve begins
    slope_length: float = 40.0  # length of the parabolic transition
    boundaries: tuple[Boundary, ...] = ()
    shoulder: float = 1.0  # asphalt beyond the outermost boundaries

    # ------------------------------------------------------------------ centre line
    def center_x(self, z):
        """Centre-line x at forward distance z."""
        z = np.asarray(z)
        return self.x0 + z * z * (self.k / 2.0 + z * (self.j / 6.0))

    def center_dx(self, z):
        """Derivative dx_c/dz (tangent of the road heading relative to the world z axis)."""
        z = np.asarray(z)
        return z * (self.k + z * (self.j / 2.0))

    def arc_length(self, z):
        """Arc length of the centre line from z=0 to z (series of sqrt(1+x'^2), exact to O(x'^4))."""
        z = np.asarray(z)
        k, j = self.k, self.j
        if k == 0.0 and j == 0.0:
            return z
        # 1/2 * integral of (k z + j z^2 / 2)^2
        return z + z * z * z * (k * k / 6.0 + z * (k * j / 8.0 + z * (j * j / 40.0)))

    def lateral(self, x, z):
        """Signed perpendicular offset d of world point (x, z) from the centre line (+ right)."""
        dxz = self.center_dx(z)
        return (x - self.center_x(z)) / np.sqrt(1.0 + dxz * dxz)

    def offset_x(self, d, z):
        """World x of the point at lateral offset d from the centre line at forward distance z."""
        dxz = self.center_dx(z)
        return self.center_x(z) + d * np.sqrt(1.0 + dxz * dxz)

    # ------------------------------------------------------------------ vertical profile
    def height(self, z):
        """Road surface height h(z) (the whole ground follows it)."""
        z = np.asarray(z)
        if not np.issubdtype(z.dtype, np.floating):
            z = z.astype(np.float64)
        if self.grade == 0.0:
            return np.zeros_like(z)
        t = np.clip(z - self.slope_start, 0.0, None)
        L = self.slope_length
        return np.where(t <= L, self.grade * t * t / (2.0 * L), self.grade * (t - L / 2.0))

    def intersect(self, a, m, cam_height: float):
        """Forward distance z where rays (x = a z, y = cam_height + m z) first meet the surface
        y = h(z); +inf where they do not (within Z_MAX). Exact, piecewise (flat, parabola, line)."""
        m = np.asarray(m)
        dt = m.dtype if np.issubdtype(m.dtype, np.floating) else np.float64
        inf = np.array(np.inf, dtype=dt)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if self.grade == 0.0:
                z = np.where(m < 0, -cam_height / m, inf)
                return np.where(z < Z_MAX, z, inf).astype(dt, copy=False)
            zb, L, g = self.slope_start, self.slope_length, self.grade
            z1 = -cam_height / m
            out = np.where((m < 0) & (z1 <= zb), z1, inf)
            # parabola: g t^2/(2L) - m t - (H + m zb) = 0, t = z - zb in (0, L]
            A = g / (2.0 * L)
            B = -m
            C = -(cam_height + m * zb)
            disc = B * B - 4.0 * A * C
            sq = np.sqrt(np.maximum(disc, 0.0))
            t1 = (-B - sq) / (2.0 * A)
            t2 = (-B + sq) / (2.0 * A)
            ok1 = (disc >= 0) & (t1 > 0) & (t1 <= L)
            ok2 = (disc >= 0) & (t2 > 0) & (t2 <= L)
            tp = np.where(ok1 & ok2, np.minimum(t1, t2), np.where(ok1, t1, np.where(ok2, t2, inf)))
            out = np.where(np.isinf(out), zb + tp, out)
            # constant grade beyond zb + L
            z3 = (cam_height + g * (zb + L / 2.0)) / (g - m)
            ok3 = (g - m > 0) & (z3 > zb + L)
            out = np.where(np.isinf(out) & ok3, z3, out)
            out = np.where(out < Z_MAX, out, inf)
        return out.astype(dt, copy=False)

    # ------------------------------------------------------------------ layout
    @property
    def left_edge(self) -> float:
        """Lateral offset of the left edge of the asphalt."""
        return min(b.d for b in self.boundaries) - self.shoulder if self.boundaries else -self.shoulder

    @property
    def right_edge(self) -> float:
        """Lateral offset of the right edge of the asphalt."""
        return max(b.d for b in self.boundaries) + self.shoulder if self.boundaries else self.shoulder

    def world_point(self, d, z) -> np.ndarray:
        """World points (..., 3) on the road surface at lateral offset d and forward distance z."""
        d, z = np.broadcast_arrays(np.asarray(d, np.float64), np.asarray(z, np.float64))
        return np.stack([self.offset_x(d, z), self.height(z), z], axis=-1)

    def z_at_arc_length(self, s) -> np.ndarray:
        """Inverse of arc_length (forward distance z where the centre line has run s metres)."""
        zs = np.linspace(0.0, 2.0 * max(float(np.max(s)), 1.0) + 1.0, 4096)
        return np.interp(s, self.arc_length(zs), zs)

    def as_dict(self) -> dict:
        """Plain-number description for sample metadata."""
        return {
            "x0": self.x0, "k": self.k, "j": self.j, "grade": self.grade,
            "slope_start": self.slope_start, "slope_length": self.slope_length,
            "shoulder": self.shoulder, "boundary_offsets": [b.d for b in self.boundaries],
            "boundary_markings": [b.marking for b in self.boundaries],
        }
