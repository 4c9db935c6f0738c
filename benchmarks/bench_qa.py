"""QA planning rate: QA per second planned for a suite from its scene-truth dicts (vlm/clips/suite_qa.suite_qa),
truths taken from the real renderer.

    python benchmarks/bench_qa.py [--cases 200] [--repeat 5]
"""

from __future__ import annotations

import argparse
import time

from lanevil_train.taxonomy import ILLUSION_NAMES
from lanevil_train.vlm.clips.clips import SEGMENTS, clip_cases, clip_truth
from lanevil_train.vlm.clips.suite_qa import suite_qa


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    start = time.perf_counter()
    clips = [(f"{case.case_id}-{segment}", case.seed, clip_truth(case, segment, size=(90, 160)))
             for case in clip_cases(args.cases, 1000000, list(ILLUSION_NAMES)) for segment in SEGMENTS]
    truth_s = time.perf_counter() - start
    start = time.perf_counter()
    count = sum(len(qas) for _ in range(args.repeat) for qas in suite_qa(clips).values())
    elapsed = time.perf_counter() - start
    print(f"scene truth: {len(clips)} base clips in {truth_s:.2f} s; QA planning: {count} QA over {args.repeat} "
          f"plans of the suite in {elapsed:.2f} s = {count / elapsed:,.0f} QA/s")


if __name__ == "__main__":
    main()
