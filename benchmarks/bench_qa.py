"""QA generation rate: QA per second from scene-truth dicts (vlm/clips/qa.make_qa), truths taken from the real renderer.

    python benchmarks/bench_qa.py [--cases 20] [--repeat 200]
"""

from __future__ import annotations

import argparse
import time

from lanevil_train.taxonomy import ILLUSION_NAMES
from lanevil_train.vlm.clips.clips import SEGMENTS, clip_cases, clip_truth
from lanevil_train.vlm.clips.qa import make_qa


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--repeat", type=int, default=200)
    args = parser.parse_args()
    truths = [(clip_truth(case, segment, size=(90, 160)), f"{case.case_id}-{segment}", case.seed)
              for case in clip_cases(args.cases, 1000000, list(ILLUSION_NAMES)) for segment in SEGMENTS]
    start = time.perf_counter()
    count = 0
    for r in range(args.repeat):
        for truth, base, seed in truths:
            count += len(make_qa(truth, base, seed + r))
    elapsed = time.perf_counter() - start
    print(f"QA generation: {count} QA from {len(truths)} clip truths x {args.repeat} seeds in {elapsed:.2f} s = "
          f"{count / elapsed:,.0f} QA/s ({count / 5 / elapsed:,.0f} clips/s)")


if __name__ == "__main__":
    main()
