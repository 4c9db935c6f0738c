"""Lane-marking paint coverage per pixel, anti-aliased by each pixel's footprint on the ground.

Boundaries are evenly spaced (one lane width apart), so every ground pixel is matched to its
nearest boundary by rounding; that boundary's stripes (at most two) are looked up in small
tables. The cost is therefore independent of the number of lanes.
"""

from __future__ import annotations

import numpy as np

from lanevil_train.sim.road import RoadGeometry

DOT_PERIOD = 1.2  # botts dots: one 0.2 m dot every 1.2 m
DOT_LENGTH = 0.2


def box_coverage(p: np.ndarray, f: np.ndarray, lo, hi) -> np.ndarray:
    """Fraction of the footprint [p - f/2, p + f/2] that lies inside [lo, hi] (box filter)."""
    h = 0.5 * f
    top = np.minimum(p + h, hi)
    bot = np.maximum(p - h, lo)
    return np.clip((top - bot) / f, 0.0, 1.0)


def dash_coverage(s: np.ndarray, fs: np.ndarray, length, period) -> np.ndarray:
    """Coverage of a periodic dash pattern (paint on [0, length) of every period) along s, blended
    to its mean length/period as the footprint approaches a period (no aliasing far away)."""
    p = np.mod(s, period)
    cov = (box_coverage(p, fs, 0.0, length) + box_coverage(p, fs, period, period + length)
           + box_coverage(p, fs, -period, length - period))
    t = np.clip(fs / period, 0.0, 1.0)
    return cov + t * (length / period - cov)


def paint_tables(road: RoadGeometry, dash_length: float, dash_gap: float):
    """Per boundary (left to right) and stripe slot (2): offset, width, dash length, dash period;
    and per boundary: is yellow, is ceramic dots."""
    n = len(road.boundaries)
    off = np.zeros((2, n), np.float32)
    wid = np.zeros((2, n), np.float32)
    dlen = np.ones((2, n), np.float32)
    dper = np.ones((2, n), np.float32)
    yellow = np.zeros(n, np.float32)
    dots = np.zeros(n, np.float32)
    for i, b in enumerate(road.boundaries):
        yellow[i] = 1.0 if b.color == "yellow" else 0.0
        for k, st in enumerate(b.stripes[:2]):
            off[k, i] = st.offset
            wid[k, i] = st.width
            if st.dots:
                dots[i] = 1.0
                dlen[k, i], dper[k, i] = DOT_LENGTH, DOT_PERIOD
            elif st.dashed:
                dlen[k, i], dper[k, i] = dash_length, dash_length + dash_gap
            else:
                dlen[k, i], dper[k, i] = 1.0, 1.0  # solid: paint covers the whole period
    return off, wid, dlen, dper, yellow, dots


def paint_alpha(road: RoadGeometry, d: np.ndarray, s: np.ndarray, fd: np.ndarray, fs: np.ndarray,
                dash_length: float, dash_gap: float, dash_phase: float):
    """Paint on the few pixels that can carry any: (pix, alpha, yellow, dots) where pix are flat
    pixel indices, alpha the paint coverage 0..1 there (before wear), yellow/dots whether the
    nearest boundary is yellow / made of ceramic dots. Other pixels have no paint."""
    bounds = road.boundaries
    empty = np.zeros(0, np.float32)
    if not bounds or all(not b.stripes for b in bounds):
        return np.zeros(0, np.intp), empty, empty, empty
    d0 = bounds[0].d
    w = (bounds[-1].d - d0) / max(len(bounds) - 1, 1)
    bi = np.rint((d - np.float32(d0)) * np.float32(1.0 / w))
    np.clip(bi, 0, len(bounds) - 1, out=bi)
    dd = d - (np.float32(d0) + bi * np.float32(w))  # offset from the nearest boundary
    reach = max(abs(st.offset) + st.width / 2 for b in bounds for st in b.stripes)
    pix = np.flatnonzero(np.abs(dd) < np.float32(reach) + fd)
    bi = bi.reshape(-1)[pix].astype(np.intp)
    dd = dd.reshape(-1)[pix]
    fd = fd.reshape(-1)[pix]
    fs = fs.reshape(-1)[pix]
    sp = s.reshape(-1)[pix] - np.float32(dash_phase)
    off, wid, dlen, dper, yellow, dots = paint_tables(road, dash_length, dash_gap)
    alpha = None
    for k in range(2):
        if not wid[k].any():
            continue
        o, wk = np.take(off[k], bi), np.take(wid[k], bi)
        across = box_coverage(dd - o, fd, -0.5 * wk, 0.5 * wk)
        if (dper[k] != 1.0).any() or (dlen[k] != 1.0).any():
            across = across * dash_coverage(sp, fs, np.take(dlen[k], bi), np.take(dper[k], bi))
        alpha = across if alpha is None else np.maximum(alpha, across)
    return pix, alpha, np.take(yellow, bi), np.take(dots, bi)
