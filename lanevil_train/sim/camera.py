"""Pinhole camera over the road: world <-> pixel mapping shared by the renderer and the illusions.

World frame (metres): x right, y up, z forward; the camera sits at (0, height_m, 0) above the
road point under it (road height 0 at z = 0). Pixel coordinates are pixel-index coordinates:
the centre of pixel (row i, column j) is (x, y) = (j, i), so rounding a point gives its pixel.
Intrinsics scale with the image size, so a 640x360 image is the same view as a 1280x720 one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: image size, horizontal FOV, mounting height, pitch (down +) and yaw (right +)."""

    width: int = 1280
    height: int = 720
    hfov_deg: float = 90.0
    height_m: float = 1.5
    pitch_deg: float = 2.0
    yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"Camera.{name}: expected a positive integer, got {value!r}")
        if not 10.0 <= self.hfov_deg <= 170.0:
            raise ValueError(f"Camera.hfov_deg: expected 10..170 degrees, got {self.hfov_deg}")
        if not 0.2 <= self.height_m <= 20.0:
            raise ValueError(f"Camera.height_m: expected 0.2..20 m, got {self.height_m}")
        if not -30.0 <= self.pitch_deg <= 30.0:
            raise ValueError(f"Camera.pitch_deg: expected -30..30 degrees, got {self.pitch_deg}")
        if not -45.0 <= self.yaw_deg <= 45.0:
            raise ValueError(f"Camera.yaw_deg: expected -45..45 degrees, got {self.yaw_deg}")

    # ----------------------------------------------------------------- intrinsics / extrinsics
    @property
    def fx(self) -> float:
        """Focal length in pixels (square pixels, so fy == fx)."""
        return (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def fy(self) -> float:
        """Vertical focal length in pixels (equal to fx)."""
        return self.fx

    @property
    def cx(self) -> float:
        """Principal point x in pixel-index coordinates (image centre)."""
        return self.width / 2.0 - 0.5

    @property
    def cy(self) -> float:
        """Principal point y in pixel-index coordinates (image centre)."""
        return self.height / 2.0 - 0.5

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def position(self) -> np.ndarray:
        """Camera centre in world metres."""
        return np.array([0.0, self.height_m, 0.0])

    @property
    def R(self) -> np.ndarray:
        """Rotation world -> camera (OpenCV camera axes: x right, y down, z forward)."""
        p, y = math.radians(self.pitch_deg), math.radians(self.yaw_deg)
        flip = np.diag([1.0, -1.0, 1.0])
        ry = np.array([[math.cos(y), 0.0, -math.sin(y)], [0.0, 1.0, 0.0], [math.sin(y), 0.0, math.cos(y)]])
        rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(p), -math.sin(p)], [0.0, math.sin(p), math.cos(p)]])
        return rx @ ry @ flip

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera rendering at another image size (intrinsics follow the width)."""
        return replace(self, width=width, height=height)

    def as_dict(self) -> dict:
        """Plain-number description for sample metadata."""
        return {
            "width": self.width, "height": self.height, "hfov_deg": self.hfov_deg,
            "height_m": self.height_m, "pitch_deg": self.pitch_deg, "yaw_deg": self.yaw_deg,
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
        }

    # ----------------------------------------------------------------- mapping
    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera-frame points (..., 3)."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape[-1] != 3:
            raise ValueError(f"Camera.to_camera: expected points of shape (..., 3), got {pts.shape}")
        return (pts - self.position) @ self.R.T

    def project(self, points: np.ndarray, return_depth: bool = False):
        """World points (..., 3) -> pixels (..., 2); with return_depth also the camera depth (..., ).

        Points behind the camera (depth <= 0) get NaN pixels.
        """
        cam = self.to_camera(points)
        depth = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * cam[..., 0] / depth + self.cx
            v = self.fy * cam[..., 1] / depth + self.cy
        behind = depth <= 1e-9
        u = np.where(behind, np.nan, u)
        v = np.where(behind, np.nan, v)
        pix = np.stack([u, v], axis=-1)
        return (pix, depth) if return_depth else pix

    def pixel_rays(self, u: np.ndarray, v: np.ndarray, dtype=np.float64) -> np.ndarray:
        """World-frame ray directions (..., 3) through pixels (u, v), scaled so that z == 1 where
        the ray points forward (direction = (a, m, 1): x and y change per metre of forward distance)."""
        u = np.asarray(u, dtype=dtype)
        v = np.asarray(v, dtype=dtype)
        xc = (u - self.cx) / self.fx
        yc = (v - self.cy) / self.fy
        rt = self.R.T.astype(dtype)  # camera -> world
        dx = rt[0, 0] * xc + rt[0, 1] * yc + rt[0, 2]
        dy = rt[1, 0] * xc + rt[1, 1] * yc + rt[1, 2]
        dz = rt[2, 0] * xc + rt[2, 1] * yc + rt[2, 2]
        return np.stack([dx, dy, dz], axis=-1)

    def ground_intersect(self, u: np.ndarray, v: np.ndarray, surface=None) -> np.ndarray:
        """Back-project pixels onto the ground: world points (..., 3), NaN where the ray misses.

        ``surface`` is anything with ``intersect(a, m, cam_height) -> z`` (a RoadGeometry); None
        means the flat plane y = 0.
        """
        rays = self.pixel_rays(u, v)
        dz = rays[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.where(dz > 1e-9, rays[..., 0] / dz, np.nan)
            m = np.where(dz > 1e-9, rays[..., 1] / dz, np.nan)
            if surface is None:
                z = np.where(m < 0, -self.height_m / m, np.nan)
            else:
                z = surface.intersect(a, m, self.height_m)
        z = np.where(np.isfinite(z), z, np.nan)
        return np.stack([a * z, self.height_m + m * z, z], axis=-1)

    def pixel_grid_rays(self, dtype=np.float32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-pixel (a, m, dz) for the whole image: ray x and y per metre forward, and the raw z
        component (<= 0 means the ray points backwards). Arrays of shape (height, width)."""
        xc = ((np.arange(self.width, dtype=np.float64) - self.cx) / self.fx)[None, :]
        yc = ((np.arange(self.height, dtype=np.float64) - self.cy) / self.fy)[:, None]
        rt = self.R.T
        dx = (rt[0, 0] * xc + rt[0, 1] * yc + rt[0, 2]).astype(dtype)
        dy = (rt[1, 0] * xc + rt[1, 1] * yc + rt[1, 2]).astype(dtype)
        dz = (rt[2, 0] * xc + rt[2, 1] * yc + rt[2, 2]).astype(dtype)
        dz_safe = np.maximum(dz, np.float32(1e-6))
        return dx / dz_safe, dy / dz_safe, dz
