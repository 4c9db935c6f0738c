"""Streaming robustness evaluation: images/s and peak memory as the suite grows.

Each size runs in a fresh process (peak RSS is per process), evaluating LaneATT-ResNet18 at the
quickstart setup (random weights: speed and memory do not depend on them) on the synthetic
illusion suite generated on the fly at 1280x720 (71 images per case).

Usage: python benchmarks/bench_evaluate.py --cases 10 40 [--batch 8 --workers 0]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SPEC = {
    "model": {"name": "laneatt", "head": {"_target_": "lanevil_train.models.laneatt.LaneATTHead", "max_lanes": 6,
                                          "lateral_n": 16, "bottom_n": 40},
              "decode": {"conf_threshold": 0.3}},
    "backbone": {"_target_": "lanevil_train.models.backbones.build_backbone", "name": "resnet18", "out_indices": [3]},
    "input_size": [112, 320],
    "crop_top": 0.4,
}


def run_one(cases: int, batch: int, workers: int) -> dict:
    import torch

    from lanevil_train.data.suites import SyntheticIllusionSuite
    from lanevil_train.evaluation.streaming import stream_evaluate
    from lanevil_train.models.factory import DetectorSpec, create_detector

    torch.set_num_threads(2)
    model = create_detector(DetectorSpec.from_build_config(SPEC))
    suite = SyntheticIllusionSuite(cases, 1000000)
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        stream_evaluate(model, suite, Path(out) / "per_image.jsonl", {"model": "bench"}, batch_size=batch,
                        num_workers=workers, progress="none")
        seconds = time.perf_counter() - t0
    return {"cases": cases, "images": len(suite), "seconds": round(seconds, 1),
            "images_per_s": round(len(suite) / seconds, 2),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--cases", type=int, nargs="+", default=[10, 40])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(run_one(args.one, args.batch, args.workers)))
        return
    for cases in args.cases:
        out = subprocess.run([sys.executable, __file__, "--one", str(cases), "--batch", str(args.batch),
                              "--workers", str(args.workers)], capture_output=True, text=True, check=True)
        print(out.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
