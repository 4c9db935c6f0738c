"""Tileable noise textures (made once, deterministically) and fast world-space sampling via cv2.remap."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np


@lru_cache(maxsize=None)
def noise_texture(size: int = 256, beta: float = 2.0, seed: int = 0) -> np.ndarray:
    """A (size, size) float32 tileable 1/f^beta noise texture, zero mean, unit std (read-only)."""
    rng = np.random.default_rng([seed, size, int(beta * 100)])
    f = np.fft.fftfreq(size)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    fr[0, 0] = 1.0
    amp = fr ** (-beta / 2.0)
    amp[0, 0] = 0.0
    phase = rng.uniform(0.0, 2.0 * np.pi, (size, size))
    tex = np.real(np.fft.ifft2(amp * np.exp(1j * phase)))
    tex = (tex - tex.mean()) / (tex.std() + 1e-12)
    out = tex.astype(np.float32)
    out.setflags(write=False)
    return out


def sample(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a tileable texture at float texel coordinates (wrapping); float32 out."""
    h, w = tex.shape[:2]
    x = np.asarray(x, dtype=np.float32)
    y = np.asarray(y, dtype=np.float32)
    # wrap into [0, size) (cheaper than np.mod; BORDER_WRAP handles the last texel's neighbour)
    mx = x - np.floor(x * np.float32(1.0 / w)) * np.float32(w)
    my = y - np.floor(y * np.float32(1.0 / h)) * np.float32(h)
    if mx.ndim != 2 or max(mx.shape) >= 32000:  # cv2.remap wants 2D maps below SHRT_MAX a side
        n = mx.size
        cols = 1024
        pad = (-n) % cols
        mx2 = np.pad(mx.reshape(-1), (0, pad)).reshape(-1, cols)
        my2 = np.pad(my.reshape(-1), (0, pad)).reshape(-1, cols)
        out = cv2.remap(tex, mx2, my2, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        return out.reshape(-1)[:n].reshape(mx.shape)
    return cv2.remap(tex, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

