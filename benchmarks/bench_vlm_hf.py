"""Benchmark: evaluation throughput of the local HF backend (HFVLM) with tiny random-weight models, 6-frame clips.

Run: ``python benchmarks/bench_vlm_hf.py [--families llava qwen2_vl] [--clips 16] [--batch-size 4]
[--max-new-tokens 16] [--height 360 --width 640]``. Builds each tiny model offline into a temporary directory,
then times `answer` (answers/s, greedy, the frames resized by the family's processor) and `answer_loss` with a
backward pass (samples/s). Prints one JSON line per family. The tiny models measure the wrapper's own cost
(processor, chat template, padding, generation loop), not a real VLM's.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from lanevil_train.vlm.backends.hf import HFVLM

# lanevil_dev (the test doubles of a source checkout, not in the wheel) is imported from the checkout root
CHECKOUT = Path(__file__).resolve().parents[1]
if str(CHECKOUT) not in sys.path:
    sys.path.insert(0, str(CHECKOUT))

QUESTIONS = ("How many lanes does the road have?", "Is the dark straight line in the left lane a lane marking?",
             "What should the ego vehicle do next?", "Is the car in front moving or stopped?")
ANSWERS = ("The road has three lanes.", "No, it is the shadow of a pole.", "Keep the lane.", "It is moving.")


def make_clips(n: int, height: int, width: int, seed: int) -> list[list[np.ndarray]]:
    """`n` clips of 6 random uint8 RGB frames of height x width."""
    rng = np.random.default_rng(seed)
    return [[rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(6)] for _ in range(n)]


def time_family(family: str, root: Path, clips, batch_size: int, max_new_tokens: int) -> dict:
    """answers/s and answer_loss samples/s (forward + backward) of one family's tiny model on `clips`."""
    from lanevil_dev.tiny_vlm import build_tiny_vlm

    vlm = HFVLM(build_tiny_vlm(family, root / family), dtype="float32", device="cpu", batch_size=batch_size,
                max_new_tokens=max_new_tokens)
    questions = [QUESTIONS[i % len(QUESTIONS)] for i in range(len(clips))]
    answers = [ANSWERS[i % len(ANSWERS)] for i in range(len(clips))]
    vlm.answer(clips[:batch_size], questions[:batch_size])  # warm-up
    start = time.perf_counter()
    generated = vlm.answer(clips, questions)
    answer_s = time.perf_counter() - start
    start = time.perf_counter()
    for first in range(0, len(clips), batch_size):
        stop = first + batch_size
        vlm.answer_loss(clips[first:stop], questions[first:stop], answers[first:stop]).sum().backward()
    loss_s = time.perf_counter() - start
    return {"family": family, "frames_as": vlm.frames_as, "clips": len(clips), "batch_size": batch_size,
            "max_new_tokens": max_new_tokens, "answers_per_s": round(len(generated) / answer_s, 2),
            "answer_loss_samples_per_s": round(len(clips) / loss_s, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", nargs="+", default=["llava", "qwen2_vl"])
    ap.add_argument("--clips", type=int, default=16)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--max-new-tokens", type=int, default=16)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    clips = make_clips(args.clips, args.height, args.width, args.seed)
    print(json.dumps({"machine": f"{platform.machine()} CPU, {torch.get_num_threads()} torch threads",
                      "frame": f"{args.height}x{args.width}", "torch": torch.__version__}))
    with tempfile.TemporaryDirectory() as root:
        for family in args.families:
            print(json.dumps(time_family(family, Path(root), clips, args.batch_size, args.max_new_tokens)))


if __name__ == "__main__":
    main()
