"""LaneATT-ResNet18 CPU speed: forward latency (batch 1) and train step time (batch 8).

Usage: python benchmarks/bench_laneatt.py [--repeats N] [--threads T] [--sizes 360x640,192x320] [--topk-anchors K]

Besides the --sizes rows (stride-32 layer4 features, LaneATT's default anchors), it always measures the
`experiment=quickstart` setup: 112x320 input, stride-16 layer3 features, 16 + 40 anchor origins.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from lanevil_train.models.backbones import build_backbone
from lanevil_train.models.laneatt import LaneATTHead

QUICKSTART = {"size": (112, 320), "out_indices": (3,), "lateral_n": 16, "bottom_n": 40}


def _targets(head: LaneATTHead, batch: int, size: tuple[int, int]) -> dict[str, torch.Tensor]:
    """Three straight lanes per image, converging upward (enough for matching to find positives)."""
    h, w = size
    lanes = [np.array([[x, h - 1.0], [w / 2 + (x - w / 2) * 0.15, 0.45 * h]]) for x in (0.15 * w, 0.5 * w, 0.85 * w)]
    return {"lanes": torch.from_numpy(np.stack([head.encode(lanes)["lanes"]] * batch))}


def _median_time(fn, repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--sizes", default="360x640,192x320")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--topk-anchors", type=int, default=None, help="official TuSimple/CULane setting: 1000")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rows = []
    setups = [(spec, {"size": tuple(int(v) for v in spec.split("x")), "out_indices": (4,)})
              for spec in args.sizes.split(",")]
    setups.append(("quickstart", QUICKSTART))
    for spec, setup in setups:
        size = setup["size"]
        bb = build_backbone("resnet18", out_indices=setup["out_indices"])
        head = LaneATTHead(bb.channels[-1], bb.strides[-1], size, topk_anchors=args.topk_anchors,
                           lateral_n=setup.get("lateral_n"), bottom_n=setup.get("bottom_n"))
        bb.eval(), head.eval()
        x1 = torch.randn(1, 3, *size)
        with torch.inference_mode():
            fwd = _median_time(lambda: head(bb(x1)), args.repeats)
            raw = head(bb(x1))
            dec = _median_time(lambda: head.decode(raw, conf_threshold=0.0), args.repeats)
        bb.train(), head.train()
        xb = torch.randn(args.batch, 3, *size)
        targets = _targets(head, args.batch, size)
        opt = torch.optim.Adam(list(bb.parameters()) + list(head.parameters()), lr=1e-4)

        def step() -> None:
            out = head.loss(head(bb(xb)), targets)
            opt.zero_grad(set_to_none=True)
            out["loss"].backward()
            opt.step()

        train = _median_time(step, max(3, args.repeats // 2), warmup=1)
        rows.append((spec, head.n_anchors, f"{head.fmap_size[0]}x{head.fmap_size[1]}", fwd * 1e3, dec * 1e3, train))
    print(f"LaneATT-ResNet18, CPU, torch {torch.__version__}, {args.threads} threads, train batch {args.batch}")
    print(f"{'input':>10} {'anchors':>7} {'fmap':>6} {'fwd b1 (ms)':>12} {'decode b1 (ms)':>15} {'train step (s)':>15}")
    for spec, a, fm, f, d, t in rows:
        print(f"{spec:>10} {a:>7} {fm:>6} {f:>12.1f} {d:>15.1f} {t:>15.2f}")


if __name__ == "__main__":
    main()
