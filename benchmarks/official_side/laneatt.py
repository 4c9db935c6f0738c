"""The official LaneATT side of the parity check (benchmarks/official_parity.py): run with the OFFICIAL environment's
python, never imported by the project's package (stdlib only at module level; the official modules are imported
inside the functions, after --repo is put on sys.path).

    python laneatt.py checkpoint --repo LaneATT --out CKPT [--seed 0] [--backbone resnet18]
    python laneatt.py predict --repo LaneATT --ckpt CKPT --data-root DATA --work WORK --out PRED.json \
        [--launch LAUNCHER.py] [--dataset culane]

``checkpoint`` builds the network with the official code (lib/config.py Config on a copy of
cfgs/laneatt_tusimple_<backbone>.yml, ``pretrained_backbone: false``), saves it with the official training's own
``Experiment.save_train_state`` (lib/experiment.py: ``{'epoch', 'model', 'optimizer', 'scheduler'}``, the plain
``state_dict`` keys), then changes values only, so that its random weights draw a few lanes: BatchNorm statistics
of road-like images, a unit-scale 1x1 conv, a class layer whose bias lets a few percent of the anchors through the
test threshold (0.2), a length of about 45 rows and offsets that bend every lane (so lanes leave the image on the
right within their rows, end near the left edge, and side anchors extend below their start).

``predict`` writes under WORK the anchor frequency file both sides read (``tusimple_anchors_freq.pt``: the layout of
the official data/tusimple_anchors_freq.pt, a 1-D int32 tensor of counts per anchor, left, bottom, right, with ties
in the top 1,000 and across its cut, as the published file has), the config copy (that frequency file, the data
root) and ``experiments/<name>/models/model_<epoch>.pt``; runs ``main.py test --exp_name <name> --cfg <copy>`` with
WORK as the current directory (the experiment folders are relative to it, lib/experiment.py l. 12-17) and copies the
TuSimple prediction file it writes (``experiments/<name>/results/epoch_<epoch>/test_predictions/
tusimple_predictions.json``, lib/experiment.py l. 134-140, lib/datasets/tusimple.py l. 117-119) to PRED.

With ``--dataset culane``, ``predict`` runs the same file under a copy of cfgs/laneatt_culane_<backbone>.yml (the
same network; the same frequency file; its test threshold set to TEST_THRESHOLD, as OURS_CULANE sets ours, since the
random weights are drawn for it) on a CULane-layout DATA and copies the tree of ``.lines.txt`` files it writes
(lib/datasets/culane.py l. 131-139, in the same test_predictions folder) to the folder PRED.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import types
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from side_cli import parse  # noqa: E402

# What the orchestrator runs on our side for this family's checkpoint ({work}: the WORK folder given to predict)
OURS = ["experiment=official_laneatt_tusimple", "backbone=resnet18",
        "model.head.anchor_frequency_file={work}/tusimple_anchors_freq.pt"]
OURS_CULANE = ["experiment=official_laneatt_culane", "backbone=resnet18",
               "model.head.anchor_frequency_file={work}/tusimple_anchors_freq.pt", "model.decode.conf_threshold=0.2"]
OFFICIAL = "lucastabelini/LaneATT@2f8583ba14eccba05e6779668bc3a38bc751984a"

EXPERIMENT = "parity_laneatt"
FREQUENCY_FILE = "tusimple_anchors_freq.pt"
N_ANCHORS = 2784  # 72 left + 128 bottom + 72 right origins x 6 / 15 / 6 angles (lib/models/laneatt.py l. 41-46)
TEST_THRESHOLD = 0.2  # cfgs/laneatt_tusimple_resnet18.yml test_parameters.conf_threshold
PASSING = 0.04  # the fraction of anchors the class bias lets through the test threshold on road-like images
INPUT_HW = (360, 640)


def _official_imports(repo: str):
    """The official Config and Experiment, with the compiled lane NMS (`nms`, which lib/models/laneatt.py imports,
    CUDA only) replaced by a keep-everything stand-in: `checkpoint` runs the forward only to see every anchor's
    score, never the test NMS."""
    repo = os.path.abspath(repo)
    if repo not in sys.path:
        sys.path.insert(0, repo)
    stub = types.ModuleType("nms")

    def keep_all(proposals, scores, overlap=0, top_k=0):
        order = scores.argsort(descending=True)
        return order, len(order), None

    stub.nms = keep_all
    sys.modules["nms"] = stub
    from lib.config import Config
    from lib.experiment import Experiment

    return Config, Experiment


def write_frequency_file(path: Path) -> Path:
    """The anchor frequency file both sides read: counts 3000 / (1 + rank / 10) truncated (so neighbouring ranks
    tie from about rank 50 on: the top 1,000 hold ties and the cut at 1,000 falls inside a tie), given to the
    anchors in a fixed shuffled order; deterministic, the same for every seed."""
    import random

    import torch

    order = list(range(N_ANCHORS))
    random.Random(1234).shuffle(order)
    counts = [0] * N_ANCHORS
    for rank, anchor in enumerate(order):
        counts[anchor] = int(3000 / (1 + rank / 10))
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(torch.tensor(counts, dtype=torch.int32), path)
    return path


def write_config(repo: str, backbone: str, frequency: Path, data_root: str, path: Path,
                 dataset: str = "tusimple") -> Path:
    """A copy of cfgs/laneatt_<dataset>_<backbone>.yml: no ImageNet weights, the given frequency file, every
    dataset root at data_root (CULane: the test threshold TEST_THRESHOLD)."""
    import yaml

    source = Path(repo) / "cfgs" / f"laneatt_{dataset}_{backbone}.yml"
    cfg = yaml.load(source.read_text(), Loader=yaml.FullLoader)
    if dataset == "culane":
        cfg["test_parameters"]["conf_threshold"] = TEST_THRESHOLD
    params = cfg["model"]["parameters"]
    params["pretrained_backbone"] = False
    params["anchors_freq_path"] = str(frequency.resolve())
    for split in cfg["datasets"].values():
        split["parameters"]["root"] = str(Path(data_root).resolve())
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.dump(cfg, sort_keys=False))
    return path


def road_images(seed: int, count: int = 4):
    """Road-like BGR / 255 inputs (a bright sky, a grey road, light slanted stripes) for the BatchNorm statistics
    and the class-bias calibration; (count, 3, 360, 640) float32."""
    import numpy as np
    import torch

    rng = np.random.default_rng(seed)
    h, w = INPUT_HW
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    out = []
    for _ in range(count):
        img = np.empty((h, w, 3))
        horizon = int(h * rng.uniform(0.3, 0.4))
        img[:horizon] = rng.uniform(0.5, 0.8, 3)
        img[horizon:] = 0.35 + rng.normal(0, 0.03, (h - horizon, w, 1))
        vanish = w / 2 + rng.uniform(-40, 40)
        for bottom in (-120 + rng.uniform(-20, 20), 165 + rng.uniform(-15, 15), 475 + rng.uniform(-15, 15),
                       765 + rng.uniform(-20, 20)):
            t = (h - 1 - ys) / (h - 1 - horizon)
            centre = bottom + (vanish - bottom) * t
            stripe = (np.abs(xs - centre) < 1 + 5 * (1 - t)) & (ys > horizon)
            img[stripe] = 0.92
        out.append(img.transpose(2, 0, 1))
    return torch.tensor(np.stack(out), dtype=torch.float32)


def set_batchnorm_statistics(model, images) -> None:
    """Trained-looking BatchNorm statistics: each layer's running mean and variance set to those of `images`
    (the cumulative average of one pass in training mode)."""
    import torch

    norms = [m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    for bn in norms:
        bn.reset_running_stats()
        bn.momentum = None  # cumulative average
    model.train()
    with torch.no_grad():
        model.feature_extractor(images)
    for bn in norms:
        bn.momentum = 0.1  # the torchvision default (not saved)
    model.eval()


def draw_lanes(model, images, seed: int) -> None:
    """Head values that draw lanes: a unit-scale 1x1 conv, a class layer that ranks anchors by their features and
    lets PASSING of them through the test threshold on `images`, a length of 45 rows plus what the features add
    (46-62 rows on the drawn test roads), offsets that bend every lane by 70 px at its top (to the right for an even
    seed, to the left for an odd one) plus a few px of the features' per row."""
    import math

    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        conv = model.conv1
        conv.weight.normal_(0.0, 1.0 / math.sqrt(conv.in_channels), generator=g)
        conv.bias.zero_()
        joint = model.cls_layer.in_features
        model.attention_layer.weight.normal_(0.0, 0.3 / math.sqrt(model.attention_layer.in_features), generator=g)
        model.cls_layer.weight.normal_(0.0, 1.0 / math.sqrt(joint), generator=g)
        model.cls_layer.bias.zero_()
        reg = model.reg_layer
        reg.weight.normal_(0.0, 1.0 / math.sqrt(joint), generator=g)
        reg.weight[0] *= 6.0
        reg.weight[1:] *= 3.0
        rows = torch.linspace(0.0, 1.0, reg.out_features - 1)  # offset k: anchor row k, bottom first
        bend = 70.0 if seed % 2 == 0 else -70.0
        reg.bias[0] = 45.0
        reg.bias[1:] = bend * rows ** 2
        # the class bias: PASSING of the anchors above the threshold on the road-like images
        logits = _proposal_logits(model, images)
        diff = (logits[..., 1] - logits[..., 0]).flatten()
        wanted = math.log(TEST_THRESHOLD / (1 - TEST_THRESHOLD))  # score 0.2 <=> logit difference log(0.25)
        shift = wanted - torch.quantile(diff, 1.0 - PASSING).item()
        model.cls_layer.bias[1] = shift / 2
        model.cls_layer.bias[0] = -shift / 2


def _proposal_logits(model, images):
    """(B, A, 2) class logits of every anchor (the official forward with no threshold; the NMS keeps all)."""
    import torch

    with torch.no_grad():
        proposals = model(images, conf_threshold=None, nms_thres=0, nms_topk=len(model.anchors))
    return torch.stack([p[:, :2] for p, _, _, _ in proposals])


def checkpoint(repo: str, out: str, seed: int = 0, backbone: str = "resnet18") -> Path:
    """An official-layout LaneATT checkpoint with random weights that draw lanes (see the module docstring)."""
    import torch

    config_cls, experiment_cls = _official_imports(repo)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    with tempfile.TemporaryDirectory() as tmp:
        frequency = write_frequency_file(Path(tmp) / FREQUENCY_FILE)
        cfg = config_cls(str(write_config(repo, backbone, frequency, tmp, Path(tmp) / "config.yml")))
        model = cfg.get_model()
        optimizer = cfg.get_optimizer(model.parameters())
        scheduler = cfg.get_lr_scheduler(optimizer)
        images = road_images(seed)
        set_batchnorm_statistics(model, images)
        draw_lanes(model, images, seed)
        # the official training's save (lib/experiment.py l. 92-100), to `out`
        saver = types.SimpleNamespace(get_checkpoint_path=lambda epoch: str(out))
        experiment_cls.save_train_state(saver, cfg["epochs"], model, optimizer, scheduler)
    return out


def _backbone_of(state: dict) -> str:
    """resnet18 or resnet34 from the official keys (layer1, feature_extractor.4, has 3 blocks in a ResNet-34)."""
    return "resnet34" if any(k.startswith("feature_extractor.4.2.") for k in state) else "resnet18"


def predict(repo: str, ckpt: str, data_root: str, work: str, out: str, launch: str | None = None,
            dataset: str = "tusimple") -> Path:
    """Run the official test entry point on data_root with ckpt; copy its TuSimple prediction file (CULane: its
    folder of .lines.txt) to out."""
    import torch

    repo, work = os.path.abspath(repo), Path(work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    saved = torch.load(ckpt, map_location="cpu")
    epoch = int(saved["epoch"])
    frequency = write_frequency_file(work / FREQUENCY_FILE)
    config = write_config(repo, _backbone_of(saved["model"]), frequency, data_root, work / f"laneatt_{dataset}.yml",
                          dataset)
    experiment = work / "experiments" / EXPERIMENT
    shutil.rmtree(experiment, ignore_errors=True)  # a previous run's results (this folder is ours)
    (experiment / "models").mkdir(parents=True)
    (experiment / "results").mkdir()
    shutil.copyfile(ckpt, experiment / "models" / f"model_{epoch:04d}.pt")
    args = ["main.py", "test", "--exp_name", EXPERIMENT, "--cfg", str(config)]
    if launch:
        command = [sys.executable, os.path.abspath(launch), repo, *args]
    else:
        command = [sys.executable, os.path.join(repo, args[0]), *args[1:]]
    done = subprocess.run(command, cwd=work)
    written = experiment / "results" / f"epoch_{epoch:04d}" / "test_predictions"
    if dataset == "tusimple":
        written = written / "tusimple_predictions.json"
    if not written.exists():
        raise SystemExit(f"the official test wrote no {written} (exit status {done.returncode})")
    if done.returncode:  # its TuSimple score runs after the file is written
        print(f"note: the official test exited with {done.returncode} after writing {written}", file=sys.stderr)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    if dataset == "tusimple":
        shutil.copyfile(written, out)
    else:
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(written, out, ignore=lambda folder, names: [n for n in names if n.endswith(".json")])
    return Path(out)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv, __doc__, ("resnet18", "resnet34"), "resnet18")  # CULane: the same network
    if args.command == "checkpoint":
        print(checkpoint(str(args.repo), str(args.out), args.seed, args.backbone))
    else:
        print(predict(str(args.repo), str(args.ckpt), str(args.data_root), str(args.work), str(args.out),
                      None if args.launch is None else str(args.launch), args.dataset))
    return 0

if __name__ == "__main__":
    sys.exit(main())
