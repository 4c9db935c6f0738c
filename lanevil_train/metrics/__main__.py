"""Command line scoring: ``python -m lanevil_train.metrics tusimple --pred P.json --gt G.json``.

Each benchmark is one ``_add_<name>(subparsers)`` function that registers its subcommand and
sets ``func`` (args -> result dict, printed as JSON, or a str printed as is); add it to ``_SUBCOMMANDS`` to
expose it. ``func`` imports its scorer
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
    """`culane`: the official CULane evaluation (TP, FP, FN, Precision, Recall, F1; F1@50, F1@75, mF1; with
    --categories the nine official scenario lists) of .lines.txt folders."""
    p = subparsers.add_parser("culane", help="CULane TP/FP/FN/Precision/Recall/F1, F1@50/F1@75/mF1 (and per "
                                             "category) of .lines.txt directories")
    p.add_argument("--pred-dir", required=True, help="predictions, <dir>/<image path sans ext>.lines.txt")
    p.add_argument("--gt-dir", required=True, help="annotations in the same layout")
    p.add_argument("--list", required=True, help="image list, one relative image path per line")
    p.add_argument("--width", type=int, default=1640, help="canvas width (official: 1640)")
    p.add_argument("--height", type=int, default=590, help="canvas height (official: 590)")
    p.add_argument("--lane-width", type=int, default=30, help="drawn lane width in px (official: 30)")
    p.add_argument("--iou", type=float, default=0.5, help="IoU threshold, strict '>' (official: 0.5)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes (default: one per CPU for long lists, >= 250 images each; 1: no extra process)")
    p.add_argument("--categories", default=None, metavar="LIST_DIR",
                   help="folder of the nine official category lists (CULane's list/test_split/: test0_normal.txt "
                        "... test8_night.txt): F1 per category, cross as its FP count")
    p.add_argument("--table", action="store_true",
                   help="print a markdown table (F1@50, F1@75, mF1 in %%, per category) instead of the JSON")

    def run(args: argparse.Namespace) -> dict | str:
        from lanevil_train.metrics.culane_files import category_table, evaluate_culane_dirs

        result = evaluate_culane_dirs(args.pred_dir, args.gt_dir, args.list, args.width, args.height,
                                      args.lane_width, args.iou, args.workers, args.categories)
        return category_table(result) if args.table else result

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


def _image_size(text: str) -> tuple[int, int]:
    """``WxH`` (e.g. 2560x1440) -> (H, W)."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 2560x1440, got {text!r}") from None
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"expected a positive WIDTHxHEIGHT, got {text!r}")
    return height, width


def _add_curvelanes(subparsers: argparse._SubParsersAction) -> None:
    """`curvelanes`: the CurveLanes evaluation (CULane's IoU F1 at 224x224, 5 px lanes: metrics/curvelanes.py) of a
    .lines.txt tree against the official .lines.json labels."""
    p = subparsers.add_parser("curvelanes", help="CurveLanes TP/FP/FN/Precision/Recall/F1 of a .lines.txt tree")
    p.add_argument("--pred-dir", required=True,
                   help="predictions, <dir>/<split>/images/<name>.lines.txt (task=evaluate task.predictions=true "
                        "writes them in predictions/culane)")
    p.add_argument("--root", required=True, help="the CurveLanes folder (<root>/<split>/<split>.txt, labels/, images/)")
    p.add_argument("--split", default="valid", help="train or valid (default: valid; test has no public labels)")
    p.add_argument("--list", default=None, help="a list file under root instead of <split>/<split>.txt")
    p.add_argument("--image-size", type=_image_size, default=None,
                   help="WIDTHxHEIGHT of every image (default: each image's own, read from its header)")
    p.add_argument("--width", type=int, default=224, help="evaluation canvas width (official: 224)")
    p.add_argument("--height", type=int, default=224, help="evaluation canvas height (official: 224)")
    p.add_argument("--lane-width", type=int, default=5, help="drawn lane width in px (official: 5)")
    p.add_argument("--iou", type=float, default=0.5, help="IoU threshold, strict '>' (official: 0.5)")

    def run(args: argparse.Namespace) -> dict:
        from lanevil_train.metrics.curvelanes import evaluate_curvelanes_dirs

        return evaluate_curvelanes_dirs(args.pred_dir, args.root, args.split, args.list, args.image_size,
                                        args.width, args.height, args.lane_width, args.iou)

    p.set_defaults(func=run)


_SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [_add_tusimple, _add_culane, _add_vqa,
                                                                    _add_curvelanes]


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
    print(result if isinstance(result, str) else json.dumps(result))  # a str: a table the command asked for
    return 0


if __name__ == "__main__":
    sys.exit(main())
