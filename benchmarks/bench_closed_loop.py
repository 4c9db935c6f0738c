"""Closed-loop speed: control steps per second of a trained detector driving the car, and where the time goes
(render the view, draw the illusion, the detector's inference, the controller and the vehicle step).

Usage: python benchmarks/bench_closed_loop.py CKPT [--runs 4] [--size 360 640] [--illusion rail_shadow]
Drives --runs runs (cases 1000000.., severity 3) and prints a markdown table of ms per step for each part and the
steps per second of the whole loop.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import lanevil_train.closed_loop.episode as episode
from lanevil_train.closed_loop import DetectorPolicy, LoopSettings, Run
from lanevil_train.closed_loop.episode import drive, illusion_region
from lanevil_train.models.factory import load_detector


def timed(totals: dict, name: str, function):
    """`function` wrapped to add its wall time to totals[name]."""
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            totals[name] += time.perf_counter() - start
    return wrapper


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt")
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--size", type=int, nargs=2, default=[360, 640])
    parser.add_argument("--illusion", default="rail_shadow")
    args = parser.parse_args()
    settings = LoopSettings(size=tuple(args.size))
    policy = DetectorPolicy(load_detector(args.ckpt))
    totals: dict[str, float] = defaultdict(float)
    episode.shade_scene = timed(totals, "render", episode.shade_scene)
    episode.get_illusion = lambda name, _get=episode.get_illusion: timed(totals, "illusion", _get(name))
    policy.lanes = timed(totals, "detector", policy.lanes)
    policy.controller.steer = timed(totals, "controller", policy.controller.steer)
    episode.step = timed(totals, "vehicle", episode.step)
    runs = []
    for i in range(args.runs):
        seed = 1000000 + i
        region = illusion_region(seed, args.illusion, settings.size)
        runs.append(Run(f"case{i}", seed, args.illusion, 3, 0, region[0] - 7.5, region))
    drive(runs[0], policy, settings)  # warm-up (caches, first inference)
    totals.clear()
    steps, start = 0, time.perf_counter()
    for run in runs:
        steps += len(drive(run, policy, settings))
    wall = time.perf_counter() - start
    print(f"{steps} steps of {args.runs} runs at {args.size[0]}x{args.size[1]}: {steps / wall:.1f} steps/s")
    print("| part | ms per step |\n|---|---:|")
    for name in ("render", "illusion", "detector", "controller", "vehicle"):
        print(f"| {name} | {1e3 * totals[name] / steps:.1f} |")
    print(f"| whole step | {1e3 * wall / steps:.1f} |")


if __name__ == "__main__":
    main()
