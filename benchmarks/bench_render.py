"""Benchmark the road-scene renderer on ONE core: median images/s at 640x360 over N scenes, and the
median time per image at 1280x720.

Usage: OMP_NUM_THREADS=1 python benchmarks/bench_render.py [--n 200] [--n-large 30]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from lanevil_train.sim import render_scene  # noqa: E402


def time_renders(seeds: range, width: int, height: int) -> np.ndarray:
    """Seconds per render_scene call (full sample: image + GT lanes + meta) for each seed."""
    out = []
    for seed in seeds:
        t0 = time.perf_counter()
        render_scene(seed, None, width, height)
        out.append(time.perf_counter() - t0)
    return np.asarray(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200, help="scenes at 640x360")
    ap.add_argument("--n-large", type=int, default=30, help="scenes at 1280x720")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    render_scene(0, None, 640, 360)  # warm-up (texture caches)
    rows = []
    for (w, h), n in (((640, 360), args.n), ((1280, 720), args.n_large)):
        t = time_renders(range(1000, 1000 + n), w, h)
        med = float(np.median(t))
        rows.append((f"{w}x{h}", n, med * 1e3, float(np.percentile(t, 90)) * 1e3, 1.0 / med))
    print(f"{'size':>10} {'scenes':>7} {'median ms':>10} {'p90 ms':>8} {'images/s':>9}")
    for size, n, med, p90, ips in rows:
        print(f"{size:>10} {n:>7d} {med:>10.1f} {p90:>8.1f} {ips:>9.1f}")
    print(f"(one core: OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}, cv2 threads={cv2.getNumThreads()})")


if __name__ == "__main__":
    main()
