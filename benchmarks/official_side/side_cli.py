"""The command line every official side script shares (benchmarks/official_parity.py runs them with the official
environment's python; standard library only):

    python <family>.py checkpoint --repo REPO --out CKPT [--seed 0] [--backbone B] [--dataset tusimple|culane]
    python <family>.py predict --repo REPO --ckpt CKPT --data-root DATA --work WORK --out OUT \\
        [--launch LAUNCHER.py] [--backbone B] [--dataset tusimple|culane]

``checkpoint`` writes an official-layout checkpoint with random weights that draw lanes; ``predict`` runs the
official test entry point on DATA with it (through LAUNCHER.py, run as ``python LAUNCHER.py REPO SCRIPT ARGS``, when
given) and copies what it wrote to OUT: the TuSimple prediction file, or for CULane the folder of ``.lines.txt``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

DATASETS = ("tusimple", "culane")


def parse(argv: list[str] | None, description: str, backbones, default_backbone: str) -> argparse.Namespace:
    """The parsed command line (``command``: checkpoint or predict; paths absolute)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    checkpoint = sub.add_parser("checkpoint", help="an official-layout checkpoint with random weights that draw lanes")
    predict = sub.add_parser("predict", help="the official test entry point's prediction file (CULane: folder)")
    for command in (checkpoint, predict):
        command.add_argument("--repo", type=Path, required=True, help="the official repository")
        command.add_argument("--out", type=Path, required=True)
        command.add_argument("--backbone", choices=sorted(backbones), default=default_backbone)
        command.add_argument("--dataset", choices=DATASETS, default="tusimple")
    checkpoint.add_argument("--seed", type=int, default=0)
    predict.add_argument("--ckpt", type=Path, required=True)
    predict.add_argument("--data-root", type=Path, required=True)
    predict.add_argument("--work", type=Path, required=True)
    predict.add_argument("--launch", type=Path, default=None, help="a launcher standing in for CUDA")
    args = parser.parse_args(argv)
    for name in ("repo", "out", "ckpt", "data_root", "work", "launch"):
        if getattr(args, name, None) is not None:
            setattr(args, name, getattr(args, name).resolve())
    return args
