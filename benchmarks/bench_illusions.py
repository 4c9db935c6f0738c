"""apply_illusion speed at 1280x720 on one core (median per illusion), recovering the ground plane from a
photo's lanes (context_from_lanes, target under 5 ms), and task=build throughput.

Usage: OMP_NUM_THREADS=1 python benchmarks/bench_illusions.py [--scenes N] [--build-images 1000 --workers 2]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time

import cv2
import numpy as np

from lanevil_train.data.illusion_set import Plan, build_illusion_set, synthetic_cases
from lanevil_train.illusions import ILLUSIONS, context_from_scene
from lanevil_train.illusions.recover import context_from_lanes
from lanevil_train.lanes import TUSIMPLE_H_SAMPLES, lanes_to_rows, rows_to_lane
from lanevil_train.sim import build_scene, render_scene, sample_scene_params


def per_illusion(scenes: int) -> dict[str, float]:
    """Median ms of each illusion (all severities) over `scenes` 1280x720 scenes, context given."""
    cases = []
    for seed in range(scenes):
        params = sample_scene_params(seed)
        cases.append((render_scene(seed, params)["image"], context_from_scene(build_scene(seed, params, 1280, 720))))
    out = {}
    for name, illusion in ILLUSIONS.items():
        times = []
        for image, ctx in cases:
            for severity in range(1, 6):
                t0 = time.perf_counter()
                illusion(image, ctx, severity, seed=1)
                times.append(time.perf_counter() - t0)
        out[name] = 1e3 * statistics.median(times)
    return out


def recover_ms(scenes: int, repeats: int = 20) -> float:
    """Median ms of context_from_lanes on the TuSimple rows (10-px rows, integer x) of `scenes` 1280x720
    scenes' lanes, as a user's photo gives them."""
    times = []
    for seed in range(scenes):
        scene = build_scene(seed, sample_scene_params(seed), 1280, 720)
        rows = np.round(lanes_to_rows(scene.lanes()[0], TUSIMPLE_H_SAMPLES))
        rows[(rows < 0) | (rows >= 1280)] = -2.0
        lanes = [rows_to_lane(r, TUSIMPLE_H_SAMPLES) for r in rows]
        for _ in range(repeats):
            t0 = time.perf_counter()
            context_from_lanes(lanes, (720, 1280))
            times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def build_rate(images: int, workers: int) -> tuple[float, int]:
    """Seconds to build about `images` synthetic 1280x720 test images (originals + all 14 x 5 variants)."""
    per_case = 1 + len(ILLUSIONS) * 5
    cases = synthetic_cases(max(1, round(images / per_case)), 1000000)
    with tempfile.TemporaryDirectory() as root:
        t0 = time.perf_counter()
        summary = build_illusion_set(cases, Plan(illusions=tuple(ILLUSIONS)), root, workers=workers,
                                     progress="none")
        return time.perf_counter() - t0, summary["images"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--build-images", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    times = per_illusion(args.scenes)
    print(f"apply_illusion at 1280x720, one core, median over {args.scenes} scenes x 5 severities (ms):")
    for name, ms in times.items():
        print(f"  {name:24s} {ms:7.1f}")
    print(f"context_from_lanes (ground plane from TuSimple rows), median: {recover_ms(args.scenes):.2f} ms")
    if args.build_images:
        seconds, images = build_rate(args.build_images, args.workers)
        print(f"task=build: {images} images in {seconds:.1f} s with {args.workers} workers "
              f"({images / seconds:.1f} images/s)")


if __name__ == "__main__":
    main()
