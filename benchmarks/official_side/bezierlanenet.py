"""The official BezierLaneNet side of the parity check (benchmarks/official_parity.py): pytorch-auto-drive's
BezierLaneNet (configs/lane_detection/bezierlanenet/resnet{18,34}_tusimple_aug1b.py), run with the OFFICIAL code's
python.

Never imported by the project's package: the module level is stdlib only (the orchestrator reads OURS and OFFICIAL
in the project's venv); the official modules are imported inside the functions, from --repo (pad_common.py).

    python bezierlanenet.py checkpoint --repo REPO --out CKPT [--seed 0] [--backbone resnet18]
    python bezierlanenet.py predict --repo REPO --ckpt CKPT --data-root DATA --work WORK --out PRED.json \
        [--launch LAUNCHER.py]

``checkpoint`` builds ``BezierLaneNet`` with the official registry from the release's config (no ImageNet weights)
and saves it with the official ``utils/common.py save_checkpoint`` (``{'model', 'optimizer', 'lr_scheduler'}``),
after changing values only, deterministically per seed, so that the random network draws lanes: the DCNv2's offset
convolution small and random (the official init is zero: offsets and masks then vary over the image); BatchNorm
statistics from a pass over seeded road-like images (pad_common.road_probe: normalised activations); the existence
projection scaled to an image-dependent part of std CLS_PART around CLS_BIAS (several local maxima above 0.5 among
the 40 queries); the curve projection's bias a lane from the bottom to the top of the image (control points' y
BOTTOM ... TOP, x BASE_X), its weights scaled so that each control point's image-dependent part has the std
CURVE_PART gives it: the bottom x spread widely (lanes leaving the image at the left and right edges), the top x
less (lanes converge), the end points' y a little (lanes ending inside the image and below its bottom).

``predict`` runs the official test entry (pad_common.run_test) and copies its ``output/<exp_name>.json``.

``--dataset culane``: the CULane release's config (resnet{18,34}_culane_aug1b.py: 288x800, existence above 0.95, at
most 4 lanes), the probe at its input size and the existence bias raised by the logit of 0.95 so that as many
queries pass its threshold; ``predict`` copies the ``.lines.txt`` tree the official test writes (a CULane-layout
DATA, ``list/test.txt``).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pad_common import COMMIT, build_model, road_probe, run_test, save  # noqa: E402
from side_cli import parse  # noqa: E402

OFFICIAL = f"voldemortX/pytorch-auto-drive@{COMMIT}"
OURS = ["experiment=official_bezierlanenet_tusimple", "backbone=resnet18"]
OURS_CULANE = ["experiment=official_bezierlanenet_culane", "backbone=resnet18"]
BACKBONES = ("resnet18", "resnet34")
CONFIG = "configs/lane_detection/bezierlanenet/{backbone}_{dataset}_aug1b.py"
EXP_NAME = "parity_bezierlanenet_{dataset}"
INPUT_SIZE = {"tusimple": (360, 640), "culane": (288, 800)}  # the configs' input_size
THRESHOLD_LOGIT = {"tusimple": 0.0, "culane": 2.944439}  # logit of the test threshold (model.thresh 0.5, 0.95)

OFFSET_STD = 0.02      # the DCN's offset convolution weights (the official init: zero)
CLS_PART = 2.0         # std of the image-dependent part of the existence logit
CLS_BIAS = -0.5        # its mean
BOTTOM, TOP = 1.02, 0.36  # the control points' y (of the height) at the curve's start and end
BASE_X = (0.8, 0.88, 0.5, 0.5)  # the control points' x on the probe (on the test images about 0.55, 0.5, 0.5, 0.5)
# std of the image-dependent part of each control point (x0, y0, x1, y1, x2, y2, x3, y3), in image fractions
CURVE_PART = (0.45, 0.05, 0.3, 0.0, 0.15, 0.0, 0.08, 0.04)


def make_checkpoint(repo: Path, out: Path, seed: int, backbone: str, dataset: str = "tusimple") -> Path:
    import torch
    from torch import nn

    torch.manual_seed(seed)
    net, _ = build_model(repo, CONFIG.format(backbone=backbone, dataset=dataset))
    generator = torch.Generator().manual_seed(seed)
    probe = road_probe(4, seed, INPUT_SIZE[dataset])
    with torch.no_grad():
        offsets = net.simple_flip_2d.proj2_conv.conv_offset
        offsets.weight.copy_(torch.randn(offsets.weight.shape, generator=generator) * OFFSET_STD)
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.reset_running_stats()
                m.momentum = None  # a cumulative average over the probe pass
        net.train()
        net(probe)
        net.eval()
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.momentum = 0.1  # the default, as saved by training
        features = _head_features(net, probe)  # (B, C, Q)
        flat = features.permute(0, 2, 1).reshape(-1, features.shape[1])  # (B * Q, C)
        cls = net.proj_classification
        part = flat @ cls.weight[:, :, 0].T
        cls.weight.mul_(CLS_PART / float(part.std()))
        cls.bias.fill_(CLS_BIAS + THRESHOLD_LOGIT[dataset])
        cls.bias.sub_(float((flat.mean(0) @ cls.weight[:, :, 0].T).item()))
        reg = net.proj_regression
        parts = flat @ reg.weight[:, :, 0].T  # (B * Q, 8)
        scale = torch.tensor(CURVE_PART) / parts.std(0)
        reg.weight.mul_(scale[:, None, None])
        ys = torch.linspace(BOTTOM, TOP, 4)
        base = torch.stack([torch.tensor(BASE_X), ys], dim=1).reshape(-1)  # x0, y0, x1, y1, ...
        reg.bias.copy_(base - flat.mean(0) @ reg.weight[:, :, 0].T)
    out = save(net, out)
    state = torch.load(out, map_location="cpu")
    print(f"{out}: {sorted(state)}; {len(state['model'])} tensors (seed {seed}, {backbone})")
    return out


def _head_features(net, x):
    """BezierLaneNet.forward (utils/models/lane_detection/bezier_lane_net.py l. 41-63) up to the regression head."""
    x = net.backbone(x)
    if isinstance(x, dict):
        x = x["out"]
    if net.reducer is not None:
        x = net.reducer(x)
    if net.dilated_blocks is not None:
        x = net.dilated_blocks(x)
    x = net.simple_flip_2d(x.float())
    x = net.aggregator(x)[:, :, 0, :]
    return net.regression_head(x)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv, __doc__, BACKBONES, "resnet18")
    if args.command == "checkpoint":
        make_checkpoint(args.repo, args.out, args.seed, args.backbone, args.dataset)
    else:
        run_test(args.repo, CONFIG.format(backbone=args.backbone, dataset=args.dataset), args.ckpt, args.data_root,
                 args.work, args.out, args.launch, EXP_NAME.format(dataset=args.dataset), args.dataset)
    return 0

if __name__ == "__main__":
    sys.exit(main())
