"""Benchmark: 6-frame clips/s from the simulator (vlm.clips.clips.render_clip), clean and with the illusion.

Run: ``python benchmarks/bench_clips.py [--cases 14] [--first-seed 1000000] [--height 360 --width 640]``.
Cases cycle through all 14 illusion types; every case renders its 3 segments. "clean" renders severity 0
only; "clean + 1 severity" renders the clean frames and the illusion at severity 3 (the clean frame is
shared); "clean + 5 severities" all of them. The reference view (one extra render and the footprint) is
computed once per case and counted in each pass (its cache is cleared first).
"""

from __future__ import annotations

import argparse
import json
import time

from lanevil_train.taxonomy import ILLUSION_NAMES
from lanevil_train.vlm.clips import clips


def rate(cases: list[clips.ClipCase], severities: list[int], size: tuple[int, int]) -> float:
    """Clips (one segment, all requested severities) per second over every case and segment."""
    clips._reference.cache_clear()
    start = time.perf_counter()
    n = 0
    for case in cases:
        for segment in clips.SEGMENTS:
            clips.render_clip(case, segment, severities, size)
            n += 1
    return n / (time.perf_counter() - start)


def main() -> None:
    """Print the clip rates as JSON."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", type=int, default=14)
    ap.add_argument("--first-seed", type=int, default=1000000)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--width", type=int, default=640)
    args = ap.parse_args()
    size = (args.height, args.width)
    cases = clips.clip_cases(args.cases, args.first_seed, ILLUSION_NAMES)
    out = {"cases": len(cases), "clips_per_pass": 3 * len(cases), "size": f"{args.width}x{args.height}",
           "clean_clips_per_s": rate(cases, [0], size),
           "clean_plus_1_severity_clips_per_s": rate(cases, [0, 3], size),
           "clean_plus_5_severities_clips_per_s": rate(cases, [0, 1, 2, 3, 4, 5], size)}
    print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}, indent=1))


if __name__ == "__main__":
    main()
