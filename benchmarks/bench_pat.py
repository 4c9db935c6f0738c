"""PAT++ on the embedded VLM: time per GCG step, peak memory, and what the tuned prefix does.

    python benchmarks/bench_pat.py --model DIR --out OUT [--train-cases 40 --test-cases 40 --steps 20]

DIR: a trained embedded VLM, e.g. the `model/` folder of `python -m lanevil_train experiment=vlm_quickstart`. Hard examples as AAM++ picks
them: the model answers the yes/no and choice questions of the train cases' perturbed clips, and a wrong answer
(accuracy below the mean) makes a hard example, a right one a benign example (its reference is the target). The
prefix is tuned on `--examples` of each, then the yes/no and choice accuracy of held-out perturbed clips is
measured without and with it. Writes OUT/prefix.json and OUT/results.json.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from bench_embedded import TEST_FIRST_SEED, clip_frames, first_answer, load_split  # noqa: E402

from lanevil_train.vlm.hf import HFVLM  # noqa: E402
from lanevil_train.vlm.pat import (Examples, GCGSettings, PrefixObjective, hard_mask, hard_target,  # noqa: E402
                                   splice_prefix, tune_prefix)
from lanevil_train.vlm.qa_records import prompt_text  # noqa: E402


def closed_pairs(clips: list[dict]) -> list[tuple[list, str, dict]]:
    """(perturbed frames, prompt, QA) for every yes/no and choice QA of the clips."""
    return [(clip_frames(clips, i, 1, False), prompt_text(qa), qa) for i, clip in enumerate(clips)
            for qa in clip["qa"] if qa["type"] in ("yes_no", "choice")]


def answers_with(vlm: HFVLM, pairs, prefix: list[int] | None, batch: int = 16) -> list[str]:
    """Greedy answers to the pairs, the prefix spliced before each question when given."""
    out = []
    tokenizer = vlm.processor.tokenizer
    for first in range(0, len(pairs), batch):
        group = pairs[first:first + batch]
        encoded = vlm.encode([p[0] for p in group], [p[1] for p in group])
        if prefix:
            encoded, _ = splice_prefix(encoded, prefix)
        with torch.no_grad():
            generated = vlm.model.generate(**encoded.inputs, max_new_tokens=vlm.max_new_tokens, do_sample=False,
                                           pad_token_id=tokenizer.pad_token_id)
        new = generated[:, encoded.inputs["input_ids"].shape[1]:]
        out += [text.strip() for text in tokenizer.batch_decode(new, skip_special_tokens=True)]
    return out


def correct(pairs, answers) -> list[float]:
    return [float(first_answer(qa, got) == first_answer(qa, qa["answer"])) for (_, _, qa), got in zip(pairs, answers)]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="a trained embedded VLM folder")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/lanevil_embedded_clips"))
    parser.add_argument("--train-cases", type=int, default=40)
    parser.add_argument("--test-cases", type=int, default=40)
    parser.add_argument("--examples", type=int, default=8, help="benign and hard examples each")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--prefix-length", type=int, default=20)
    parser.add_argument("--top-k", type=int, default=256)
    parser.add_argument("--candidates", type=int, default=128)
    parser.add_argument("--chunk", type=int, default=64)
    parser.add_argument("--alpha", type=float, default=0.6)
    parser.add_argument("--hard-target", default="goal")
    parser.add_argument("--frame-size", type=int, nargs=2, default=(64, 112))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    size = tuple(args.frame_size)

    vlm = HFVLM(args.model, dtype="float32", device="cpu", max_new_tokens=24)
    train = closed_pairs(load_split(0, args.train_cases, size, args.cache, 2))
    test = closed_pairs(load_split(TEST_FIRST_SEED, args.test_cases, size, args.cache, 2))
    train_right = correct(train, answers_with(vlm, train, None))
    hard = [p for p, h in zip(train, hard_mask(train_right)) if h][:args.examples]
    benign = [p for p, h in zip(train, hard_mask(train_right)) if not h][:args.examples]
    print(f"train accuracy {np.mean(train_right):.3f}: {len(hard)} hard, {len(benign)} benign examples used")
    objective = PrefixObjective(
        vlm, Examples([p[0] for p in benign], [p[1] for p in benign], [p[2]["answer"] for p in benign]),
        Examples([p[0] for p in hard], [p[1] for p in hard], [hard_target(p[2]["answer"], args.hard_target)
                                                               for p in hard]),
        alpha=args.alpha, chunk=args.chunk)
    settings = GCGSettings(steps=args.steps, prefix_length=args.prefix_length, top_k=args.top_k,
                           num_candidates=args.candidates)
    started = time.perf_counter()
    record = tune_prefix(objective, settings, args.out, progress="plain", facts={"model": str(args.model)})
    seconds = time.perf_counter() - started
    before, after = correct(test, answers_with(vlm, test, None)), correct(test, answers_with(vlm, test, record["ids"]))
    results = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
               "seconds_per_step": seconds / args.steps, "peak_rss_mib": resource.getrusage(
                   resource.RUSAGE_SELF).ru_maxrss / 1024, "loss_first": record["history"][0],
               "loss_last": record["history"][-1], "terms": record["terms"], "prefix": record["text"],
               "test_questions": len(test), "test_accuracy_without": float(np.mean(before)),
               "test_accuracy_with": float(np.mean(after)), "train_accuracy": float(np.mean(train_right))}
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
