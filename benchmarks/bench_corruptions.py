"""Corruption speed: ms per image at severity 3 through `Corruption.__call__` next to the same albumentations
transform called directly (`transform(image=image)["image"]`), at 720x1280 and 360x640; the wrapper's overhead
(input checks + reseeding) should be ~0.

Usage: OMP_NUM_THREADS=1 python benchmarks/bench_corruptions.py [--repeats 5] [--severity 3] [--sizes 720x1280 360x640]
Prints a markdown table: medians of --repeats timed calls (wrapper and direct alternating) after one warm-up each.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import cv2
import numpy as np

from lanevil_train.corruptions import CORRUPTIONS
from lanevil_train.sim import render_scene, sample_scene_params


def paired_ms(wrapped: Callable[[], object], direct: Callable[[], object], repeats: int) -> tuple[float, ...]:
    """Median ms of `wrapped`, of `direct`, and of their per-repeat difference; the two alternate within each repeat
    (after one untimed warm-up of each), so both see the same machine load."""
    wrapped(), direct()
    times: list[tuple[float, float]] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        wrapped()
        t1 = time.perf_counter()
        direct()
        times.append((t1 - t0, time.perf_counter() - t1))
    return tuple(1e3 * statistics.median(v) for v in (*zip(*times), [w - d for w, d in times]))


def parse_size(text: str) -> tuple[int, int]:
    """'720x1280' -> (720, 1280), height first."""
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be HEIGHTxWIDTH, e.g. 720x1280, got {text!r}") from None
    return height, width


def bench(sizes: list[tuple[int, int]], severity: int, repeats: int) -> list[list[str]]:
    """One row per corruption: wrapper and direct ms at each size, and the wrapper's overhead in ms (median of the
    paired differences)."""
    images = {size: render_scene(0, sample_scene_params(0), width=size[1], height=size[0])["image"] for size in sizes}
    rows = []
    for name, corruption in CORRUPTIONS.items():
        transform = corruption.transform(severity)
        row = [name]
        for image in images.values():
            wrapped, direct, overhead = paired_ms(lambda c=corruption, im=image: c(im, None, severity, 0),
                                                  lambda t=transform, im=image: t(image=im)["image"], repeats)
            row += [f"{wrapped:.2f}", f"{direct:.2f}", f"{overhead:+.2f}"]
        rows.append(row)
    return rows


def fixed_cost_us(repeats: int = 2000) -> dict[str, float]:
    """The wrapper's fixed cost per call in microseconds (input checks + reseeding the transform), measured as the
    median paired difference on a 64x160 image, where the transforms themselves take little time."""
    image = render_scene(0, sample_scene_params(0), width=160, height=64)["image"]
    out = {}
    for name in ("brightness", "gaussian_noise", "snow"):
        corruption = CORRUPTIONS[name]
        transform = corruption.transform(3)
        out[name] = 1e3 * paired_ms(lambda c=corruption: c(image, None, 3, 0),
                                    lambda t=transform: t(image=image)["image"], repeats)[2]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--severity", type=int, default=3, choices=range(1, 6))
    parser.add_argument("--sizes", type=parse_size, nargs="+", default=[(720, 1280), (360, 640)])
    parser.add_argument("--threads", type=int, default=1, help="cv2.setNumThreads (default 1: one core)")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    cv2.setNumThreads(args.threads)
    rows = bench(args.sizes, args.severity, args.repeats)
    header = ["corruption"]
    for height, width in args.sizes:
        header += [f"{height}x{width} wrapper ms", f"{height}x{width} direct ms", f"{height}x{width} overhead ms"]
    print(f"severity {args.severity}, median of {args.repeats} calls, cv2 threads {args.threads}, "
          f"numpy {np.__version__}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    fixed = ", ".join(f"{name} {us:+.0f} us" for name, us in fixed_cost_us().items())
    print(f"\nwrapper fixed cost per call (64x160, median of 2000 paired calls): {fixed}")


if __name__ == "__main__":
    main()
