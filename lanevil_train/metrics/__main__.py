"""Command line scoring: ``python -m lanevil_train.metrics tusimple --pred P.json --gt G.json``.

Each benchmark is one ``_add_<name>(subparsers)`` function that registers its subcommand and
sets ``func`` (args -> result dict); add it to ``_SUBCOMMANDS`` to expose it. ``func`` imports its scorer
when it runs, and the package exports lazily, so a command loads what its scorer needs (numpy; OpenCV for
CULane) and never torch (tests/metrics/test_commands.py checks this in a fresh process).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from typing import Callable, Sequence


def _add_tusimple(subparsers: argparse._SubParsersAction) -> None:
    """`tusimple`: the official TuSimple file-level evaluation (Accuracy, FP, FN, F1), plus the lane-count F1_count
    and its TP/FP/FN lane counts (metrics/tusimple.py)."""
    p = subparsers.add_parser("tusimple", help="TuSimple Accuracy/FP/FN/F1 (and the lane-count F1_count) of a "
                                               "JSON-lines prediction file")
    p.add_argument("--pred", required=True, help="predictions, JSON lines {lanes, raw_file[, run_time]}")
    p.add_argument("--gt", required=True, help="ground truth, JSON lines {lanes, h_samples, raw_file}")
    p.add_argument("--pixel-thresh", type=float, default=20.0, help="pixel threshold (official: 20)")
    p.add_argument("--pt-thresh", type=float, default=0.85, help="lane match threshold (official: 0.85)")

    def run(args: argparse.Namespace) -> dict:
        from lanevil_train.metrics.tusimple import evaluate_tusimple_files

        return evaluate_tusimple_files(args.pred, args.gt, args.pixel_thresh, args.pt_thresh)

    p.set_defaults(func=run)


def _add_culane(subparsers: argparse._SubParsersAction) -> None:
    """`culane`: the official CULane evaluation (TP, FP, FN, Precision, Recall, F1) of .lines.txt folders."""
    p = subparsers.add_parser("culane", help="CULane TP/FP/FN/Precision/Recall/F1 of .lines.txt directories")
    p.add_argument("--pred-dir", required=True, help="predictions, <dir>/<image path sans ext>.lines.txt")
    p.add_argument("--gt-dir", required=True, help="annotations in the same layout")
    p.add_argument("--list", required=True, help="image list, one relative image path per line")
    p.add_argument("--width", type=int, default=1640, help="canvas width (official: 1640)")
    p.add_argument("--height", type=int, default=590, help="canvas height (official: 590)")
    p.add_argument("--lane-width", type=int, default=30, help="drawn lane width in px (official: 30)")
    p.add_argument("--iou", type=float, default=0.5, help="IoU threshold, strict '>' (official: 0.5)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes (default: one per CPU for long lists, >= 250 images each; 1: no extra process)")

    def run(args: argparse.Namespace) -> dict:
        from lanevil_train.metrics.culane_files import evaluate_culane_dirs

        return evaluate_culane_dirs(
            args.pred_dir, args.gt_dir, args.list, args.width, args.height, args.lane_width, args.iou, args.workers
        )

    p.set_defaults(func=run)


def _add_vqa(subparsers: argparse._SubParsersAction) -> None:
    """`vqa`: COCO caption scores (BLEU-1..4, ROUGE-L, CIDEr, METEOR) and DriveLM's Language score of answers."""
    p = subparsers.add_parser("vqa", help="BLEU/ROUGE-L/CIDEr/METEOR and the Language score of VQA answers")
    p.add_argument("--pred", required=True, help='answers, {"id": "answer"} or [{"id", "answer"}, ...]')
    p.add_argument("--gt", required=True, help='references, {"id": "reference" or ["reference", ...]}')
    p.add_argument("--no-meteor", action="store_true", help="skip METEOR (its Java start takes seconds)")

    def run(args: argparse.Namespace) -> dict:
        from lanevil_train.metrics.vqa import evaluate_vqa_files

        return evaluate_vqa_files(args.pred, args.gt, meteor=not args.no_meteor)

    p.set_defaults(func=run)


_SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [_add_tusimple, _add_culane, _add_vqa]


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser with one subcommand per benchmark."""
    parser = argparse.ArgumentParser(prog="python -m lanevil_train.metrics", description=__doc__.splitlines()[0])
    subparsers = parser.add_subparsers(dest="command", required=True)
    for add in _SUBCOMMANDS:
        add(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv``, score, print the result as JSON (warnings on stderr); exit code 1 with a message on bad input."""
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        try:
            result = args.func(args)
        except (ValueError, FileNotFoundError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 1
    for warning in caught:  # e.g. prediction lines the official arithmetic reads in its own way
        print(f"warning: {warning.message}", file=sys.stderr)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
