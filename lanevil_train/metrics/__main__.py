"""Command line scoring: ``python -m lanevil_train.metrics tusimple --pred P.json --gt G.json``.

Each benchmark is one ``_add_<name>(subparsers)`` function that registers its subcommand and
sets ``func`` (args -> result dict); add it to ``_SUBCOMMANDS`` to expose it.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable, Sequence


def _add_tusimple(subparsers: argparse._SubParsersAction) -> None:
    """`tusimple`: the official TuSimple file-level evaluation (Accuracy, FP, FN, F1)."""
    p = subparsers.add_parser("tusimple", help="TuSimple Accuracy/FP/FN/F1 of a JSON-lines prediction file")
    p.add_argument("--pred", required=True, help="predictions, JSON lines {lanes, raw_file[, run_time]}")
    p.add_argument("--gt", required=True, help="ground truth, JSON lines {lanes, h_samples, raw_file}")
    p.add_argument("--pixel-thresh", type=float, default=20.0, help="pixel threshold (official: 20)")
    p.add_argument("--pt-thresh", type=float, default=0.85, help="lane match threshold (official: 0.85)")

    def run(args: argparse.Namespace) -> dict:
        from lanevil_train.metrics.tusimple import evaluate_tusimple_files

        return evaluate_tusimple_files(args.pred, args.gt, args.pixel_thresh, args.pt_thresh)

    p.set_defaults(func=run)


_SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [_add_tusimple]


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser with one subcommand per benchmark."""
    parser = argparse.ArgumentParser(prog="python -m lanevil_train.metrics", description=__doc__.splitlines()[0])
    subparsers = parser.add_subparsers(dest="command", required=True)
    for add in _SUBCOMMANDS:
        add(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv``, score, print the result as JSON; exit code 1 with a message on bad input."""
    args = build_parser().parse_args(argv)
    try:
        result = args.func(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
