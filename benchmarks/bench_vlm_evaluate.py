"""End-to-end VLM evaluation throughput: answers/s of `evaluate_clips` (answering, PTB tokenising, judging, writing
per_answer.jsonl) and of the tables built from it, on a clip suite written to disk first.

    python benchmarks/bench_vlm_evaluate.py [--cases 2] [--height 360 --width 640] [--judge minilm|none]

Backends: a tiny random-weight Qwen2-VL saved on disk (lanevil_dev/tiny_vlm.py; the wrapper's and the pipeline's
own cost, not a real VLM's) and the local fake OpenAI-compatible server (lanevil_dev/fake_server.py; 50 ms per
request, concurrency 8). One JSON line each.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from lanevil_train.evaluation.results import write_results
from lanevil_train.vlm.answer_scoring.evaluation import evaluate_clips
from lanevil_train.vlm.backends.hf import HFVLM
from lanevil_train.vlm.backends.openai import OpenAIVLM
from lanevil_train.vlm.clips.clip_set import ClipSetDataset, build_clip_set
from lanevil_train.vlm.clips.clips import clip_cases

# lanevil_dev (the test doubles of a source checkout, not in the wheel) is imported from the checkout root
CHECKOUT = Path(__file__).resolve().parents[1]
if str(CHECKOUT) not in sys.path:
    sys.path.insert(0, str(CHECKOUT))


def timed(label: str, vlm, suite, judge, work: Path) -> dict:
    out = work / label
    start = time.perf_counter()
    results = evaluate_clips(vlm, suite, out, {"model": label, "dataset": "bench"}, judge=judge, progress="none")
    answered = time.perf_counter() - start
    write_results([results], out)
    total = time.perf_counter() - start
    answers = sum(1 for _ in open(results))
    return {"backend": label, "answers": answers, "answers_per_s": round(answers / answered, 2),
            "evaluate_s": round(answered, 1), "tables_s": round(total - answered, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=2)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--judge", choices=("minilm", "none"), default="minilm")
    args = parser.parse_args()
    from lanevil_dev.fake_server import FakeServer
    from lanevil_dev.tiny_vlm import build_tiny_vlm

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        cases = clip_cases(args.cases, 1000000, ["road_repair", "rail_shadow", "vehicle", "sunlight_reflection"])
        start = time.perf_counter()
        build_clip_set(cases, (1, 3, 5), work / "suite", size=(args.height, args.width), progress="none")
        print(json.dumps({"suite": "built", "cases": args.cases, "seconds": round(time.perf_counter() - start, 1)}))
        suite = ClipSetDataset(work / "suite")
        judge = None
        if args.judge == "minilm":
            from lanevil_train.vlm.answer_scoring.judge import EmbeddingJudge

            judge = EmbeddingJudge()
        hf = HFVLM(build_tiny_vlm("qwen2_vl", work / "tiny"), max_new_tokens=16, batch_size=4)
        print(json.dumps(timed("tiny-qwen2-vl", hf, suite, judge, work)))
        with FakeServer("--delay-ms", "50", "--no-decode") as server:
            vlm = OpenAIVLM(server.url, "fake", concurrency=8, image_format="jpeg")
            print(json.dumps(timed("fake-server-jpeg-c8", vlm, suite, judge, work)))


if __name__ == "__main__":
    main()
