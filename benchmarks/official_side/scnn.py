"""The official SCNN side of the parity check (benchmarks/official_parity.py): pytorch-auto-drive's VGG-16 SCNN
(configs/lane_detection/scnn/vgg16_tusimple.py, vgg16_culane.py), run with the OFFICIAL code's python.

Never imported by the project's package: the module level is stdlib only (the orchestrator reads OURS and OFFICIAL
in the project's venv); the official modules are imported inside the functions, from --repo (pad_common.py).

    python scnn.py checkpoint --repo REPO --out CKPT [--seed 0] [--backbone vgg16_bn] [--dataset tusimple]
    python scnn.py predict --repo REPO --ckpt CKPT --data-root DATA --work WORK --out PRED.json \
        [--launch LAUNCHER.py] [--dataset tusimple]

``checkpoint`` builds ``DeepLabV1`` with the official registry from the release's config (no ImageNet weights) and
saves it with the official ``utils/common.py save_checkpoint`` (``{'model', 'optimizer', 'lr_scheduler'}``), after
changing values only, so that the random network draws the test images' painted lanes, one lane class per
direction from a vanishing point:

- a "brightness" path through channel 0 of every convolution of the encoder and fc67 (the first convolution: the
  mean of the normalised RGB minus BRIGHT_CUT at the centre tap, the others the previous channel 0 at the centre
  tap; BatchNorms at mean 0, variance 1: white paint passes, grey road and sky do not), ending as channel 2 of the
  128-channel map; every other channel keeps its random weights (they do not feed the three designed channels);
- the message passing makes channel 0 count rows and channel 1 count columns (conv_d / conv_r pass the channel on
  with a bias of 1 at the centre tap; the designed channels are left alone by the other passes);
- fc8: the background logit BACKGROUND; lane class k: PAINT x brightness + SLOPE x the cell's offset from the apex
  along the class's direction (DATASETS; so on paint the class whose direction is closest to the paint's bearing
  from the apex wins, away from paint the background), plus NOISE x a fixed random mix of the random channels;
- the existence head: class k's logit is gain_k x (the mean of its probability map - mass_k) (DATASETS).

The lanes exercise the official decoding's edges: the 9 x 9 box blur before the row's arg-max, a lane leaving the
image at the left edge (arg-max column 0 is no point in the official coordinates) and one at the right edge,
dashed lanes (rows without a point inside a lane), lanes ending at the top near the apex, and six existing slots
on two images (the official keeps the five most confident, dropping a lane).

``predict`` runs the official test entry (pad_common.run_test) and copies what it writes: TuSimple its
``output/<exp_name>.json`` to PRED.json; CULane (``--dataset culane``: DATA a CULane layout, ``list/test.txt``
naming 1640x590 images) its ``output/`` tree of ``.lines.txt`` files to the folder PRED.json names.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pad_common import COMMIT, build_model, run_test, save  # noqa: E402
from side_cli import parse  # noqa: E402

OFFICIAL = f"voldemortX/pytorch-auto-drive@{COMMIT}"

OURS = ["experiment=official_scnn_tusimple", "backbone=vgg16_bn"]
OURS_CULANE = ["experiment=official_scnn_culane", "backbone=vgg16_bn"]
BACKBONES = ("vgg16_bn",)

BRIGHT_CUT = 1.3          # the first convolution's bias on the normalised RGB mean (white paint ~2.1, sky ~1.0)
PAINT = 15.0              # a lane class's logit per unit of brightness
BACKGROUND = 8.5          # the background logit
SLOPE = 0.15              # a lane class's logit per cell along its direction from the apex
SCNN_SCALE = 0.25         # the random message-passing weights scaled down: sums over 80 columns stay bounded
NOISE = 0.1               # std of the random-channel part of every class logit (relative, on the random channels)

# Per dataset: the release's config; the apex (column, row) of the stride-8 map near the images' vanishing point;
# per lane class, the direction (degrees, y down) of its wedge and the existence head's (gain, mass): its logit is
# gain x (the class's mean probability on the stride-8 map - mass).
DATASETS = {
    # 80 x 45 map of 640 x 360: apex at input (320, 125); the painted lanes' bearings ~152, 123, 57, 28 degrees.
    # On the four test images classes 1-3 and the empty class 4 always exist; class 5 (the right lane) exists with
    # the lowest confidence, and the empty class 6 exists on two images, where the official keeps 5 of the 6
    # slots (lane_pruning) and so drops the right lane; on the other two it is kept.
    "tusimple": {
        "config": "configs/lane_detection/scnn/vgg16_tusimple.py",
        "exp_name": "parity_vgg16_scnn_tusimple",
        "apex": (39.6, 15.3),
        "directions": (152.0, 57.0, 123.0, 270.0, 28.0, 90.0),
        "exist": ((600.0, 0.004), (600.0, 0.004), (600.0, 0.004), (600.0, -0.01), (600.0, 0.0205), (2000.0, 0.009)),
    },
    # 100 x 36 map of 800 x 288 (the test images stretched to 1640 x 590): apex at input (400, 100); bearings ~161,
    # 136, 44, 19 degrees
    "culane": {
        "config": "configs/lane_detection/scnn/vgg16_culane.py",
        "exp_name": "parity_vgg16_scnn_culane",
        "apex": (49.6, 12.2),
        "directions": (161.0, 44.0, 136.0, 19.0),
        "exist": ((600.0, 0.004),) * 4,
    },
}


def _designed(net, seed: int, setting: dict) -> None:
    """Set the values described in the module docstring (in place, no key or shape changed)."""
    import torch
    from torch import nn

    generator = torch.Generator().manual_seed(seed)
    convs = [m for m in net.encoder.net if isinstance(m, nn.Conv2d)] + [net.fc67[0], net.fc67[3]]
    norms = [m for m in net.modules() if isinstance(m, nn.BatchNorm2d)]
    with torch.no_grad():
        for bn in norms:
            bn.reset_running_stats()  # mean 0, variance 1
            bn.weight.fill_(1.0)
            bn.bias.zero_()
        for i, conv in enumerate(convs):
            centre = (conv.kernel_size[0] // 2, conv.kernel_size[1] // 2)
            out = 2 if conv is net.fc67[3] else 0
            conv.weight[out].zero_()
            if i == 0:
                conv.weight[0, :, centre[0], centre[1]] = 1.0 / 3.0
                conv.bias[0] = -BRIGHT_CUT
            else:
                conv.weight[out, 0, centre[0], centre[1]] = 1.0
                if conv.bias is not None:
                    conv.bias[out] = 0.0
            if conv is net.fc67[3]:
                conv.weight[:2].zero_()  # the two counters start at 0
        scnn = net.scnn
        for conv in (scnn.conv_d, scnn.conv_u, scnn.conv_r, scnn.conv_l):
            conv.weight.mul_(SCNN_SCALE)
            conv.weight[:3].zero_()
            conv.bias[:3] = 0.0
        scnn.conv_d.weight[0, 0, 0, 4] = 1.0  # row counter: slice i = relu(slice i - 1 + 1)
        scnn.conv_d.bias[0] = 1.0
        scnn.conv_r.weight[1, 1, 4, 0] = 1.0  # column counter
        scnn.conv_r.bias[1] = 1.0
        fc8 = net.fc8[1]
        classes, channels = fc8.weight.shape[:2]
        mix = torch.randn(classes, channels - 3, generator=generator) * (NOISE / math.sqrt(channels - 3))
        fc8.weight.zero_()
        fc8.weight[:, 3:, 0, 0] = mix
        fc8.bias.zero_()
        fc8.bias[0] = BACKGROUND
        apex = setting["apex"]
        for k, degrees in enumerate(setting["directions"], start=1):
            ux, uy = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
            fc8.weight[k, 2, 0, 0] = PAINT
            fc8.weight[k, 1, 0, 0] = SLOPE * ux
            fc8.weight[k, 0, 0, 0] = SLOPE * uy
            fc8.bias[k] = -SLOPE * (ux * apex[0] + uy * apex[1])
        head = net.lane_classifier
        cells = head.linear1.in_features // classes
        head.linear1.weight.zero_()
        head.linear1.bias.zero_()
        head.linear2.weight.zero_()
        for k in range(classes - 1):
            gain, mass = setting["exist"][k]
            head.linear1.weight[k, (k + 1) * cells:(k + 2) * cells] = gain / cells
            head.linear2.weight[k, k] = 1.0
            head.linear2.bias[k] = -gain * mass


def make_checkpoint(repo: Path, out: Path, seed: int, backbone: str, dataset: str) -> Path:
    import torch

    torch.manual_seed(seed)
    setting = DATASETS[dataset]
    net, _ = build_model(repo, setting["config"])
    _designed(net, seed, setting)
    out = save(net, out)
    state = torch.load(out, map_location="cpu")
    print(f"{out}: {sorted(state)}; {len(state['model'])} tensors (seed {seed}, {backbone}, {dataset})")
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse(argv, __doc__, BACKBONES, "vgg16_bn")
    if args.command == "checkpoint":
        make_checkpoint(args.repo, args.out, args.seed, args.backbone, args.dataset)
    else:
        setting = DATASETS[args.dataset]
        run_test(args.repo, setting["config"], args.ckpt, args.data_root, args.work, args.out, args.launch,
                 setting["exp_name"], args.dataset)
    return 0

if __name__ == "__main__":
    sys.exit(main())
