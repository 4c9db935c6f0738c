"""The official UFLD v1 side of the parity check (benchmarks/official_parity.py): run with the OFFICIAL code's python.

Never imported by the project's package: the module level is stdlib only (the orchestrator reads OURS and OFFICIAL
in the project's venv); the official modules are imported inside the functions, from --repo.

    python ufld.py checkpoint --repo REPO --out CKPT [--seed 0] [--backbone resnet18] [--dataset tusimple]
    python ufld.py predict --repo REPO --ckpt CKPT --data-root DATA --work WORK --out PRED.json \
        [--launch LAUNCHER.py] [--dataset tusimple]

``checkpoint`` builds the network as the official training does (train.py: ``parsingNet(backbone=...,
cls_dim=(griding_num + 1, rows, num_lanes), use_aux=cfg.use_aux)``, the dataset's config for griding_num and
use_aux, Adam as utils/factory.py get_optimizer) and saves it with the training's own ``utils/common.py save_model``
(``{'model': state_dict, 'optimizer': ...}``, no ``module.`` prefix: a single-process run). Then it changes values
only, deterministically per seed, so that random weights draw lanes: BatchNorm statistics from a pass over seeded
noise images (normalised activations), the row classifier's weights scaled to a small image-dependent part and its
bias set to four lane-shaped logit patterns (a Gaussian bump over the cells around a lane's cell at each row, the
no-lane class above or below the bump's peak). The lanes exercise the official writers' edges: one runs to the
left edge (its lower rows no lane) with no-lane rows inside it, two are short (1 and 2 points on TuSimple, whose
writer keeps every lane; 2 and 3 on CULane, whose writer keeps those with more than 2 points), one runs into the
last cell (its x past the image's right edge), and the no-lane class is close to the peak at the long lanes' ends,
so the image-dependent part decides there.

``predict`` runs the official test entry (``test.py configs/<dataset>.py --test_model CKPT --data_root DATA
--test_work_dir WORK/test``) and copies what it writes: TuSimple ``WORK/test/tusimple_eval_tmp.txt`` to PRED.json;
CULane the ``WORK/test/culane_eval_tmp/`` tree of ``.lines.txt`` files to the folder PRED.json names (the official
CULane scoring that follows needs the compiled ``evaluation/culane/evaluate``; its failure after the files are
written is expected and reported).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from side_cli import parse  # noqa: E402

OFFICIAL = "cfzd/Ultra-Fast-Lane-Detection@353df107756b8c03c22c27201e33fc63d84ecfe6"
OURS = ["experiment=official_ufld_tusimple", "backbone=resnet18"]
OURS_CULANE = ["experiment=official_ufld_culane", "backbone=resnet18"]

# dataset -> (config file, griding_num, row anchors): test.py l. 22-27, configs/tusimple.py, configs/culane.py
DATASETS = {"tusimple": ("configs/tusimple.py", 100, 56), "culane": ("configs/culane.py", 200, 18)}
NUM_LANES = 4
BACKBONES = {"resnet18": "18", "resnet34": "34"}

PEAK = 6.0            # the logit of a lane's bump at its nearest cell
SPREAD = 1.3          # the bump's width in cells: the expectation lands between cells
PRESENT = 2.5         # the no-lane logit on a lane's rows (below the peak)
ABSENT = 9.0          # ... and off them
EDGE = 5.6            # ... at a lane's first and last rows: the image-dependent part decides
IMAGE_PART = 0.45     # std of the image-dependent part of every logit


def _lane_patterns(num_cells: int, num_rows: int):
    """Per lane: (cell position mu at each row, rows on which it is present, the no-lane logit at its end rows),
    rows top first (t in [0, 1])."""
    import numpy as np

    t = np.linspace(0.0, 1.0, num_rows)
    g = num_cells / 100.0  # the patterns in TuSimple's 100-cell units
    lanes = []
    rows = np.arange(num_rows)
    wide = num_rows > 20  # TuSimple's 56 rows, not CULane's 18
    # 0: runs down to the left edge, its rows ending where mu leaves the image, with no-lane rows inside it
    mu = g * (40.0 - 50.0 * t)
    hole = (t > 0.4) & (t < 0.46) if wide else rows == 7
    lanes.append((mu, (t >= 0.1) & (mu > -0.3) & ~hole, EDGE))
    # 1 and 2: short lanes of 1 and 2 rows on TuSimple (its writer keeps every lane), 2 and 3 rows on CULane (its
    # writer only those with more than 2 points); all their rows well inside (no image decides them)
    for k, (mu, first) in enumerate([(g * (46.0 - 18.0 * t), int(round(0.3 * (num_rows - 1)))),
                                     (g * (54.0 + 22.0 * t), int(round(0.6 * (num_rows - 1))))]):
        length = k + (1 if wide else 2)
        lanes.append((mu, (rows >= first) & (rows < first + length), PRESENT))
    # 3: into the last cell (past the right edge) at the bottom
    mu = g * (60.0 + 50.0 * t)
    lanes.append((mu, t >= 0.05, EDGE))
    return lanes


def _bias(num_cells: int, num_rows: int):
    """The row classifier's bias, (griding_num + 1, rows, lanes) flattened as model/model.py l. 90 views it."""
    import numpy as np

    logits = np.zeros((num_cells + 1, num_rows, NUM_LANES))
    cells = np.arange(num_cells)[:, None]
    for k, (mu, present, edge) in enumerate(_lane_patterns(num_cells, num_rows)):
        bump = -((cells - mu[None, :]) ** 2) / (2.0 * SPREAD ** 2)
        logits[:num_cells, :, k] = bump - bump.max(axis=0, keepdims=True) + PEAK
        no_lane = np.where(present, PRESENT, ABSENT)
        rows = np.flatnonzero(present)
        if len(rows):
            no_lane[[rows[0], rows[-1]]] = edge
        logits[num_cells, :, k] = no_lane
    return logits.reshape(-1)


def make_checkpoint(repo: Path, out: Path, seed: int, backbone: str, dataset: str) -> Path:
    sys.path.insert(0, str(repo))
    import numpy as np
    import torch
    from model.model import parsingNet
    from utils.common import save_model
    from utils.config import Config
    from utils.factory import get_optimizer

    config, cells, rows = DATASETS[dataset]
    cfg = Config.fromfile(str(repo / config))
    cfg.backbone = BACKBONES[backbone]
    torch.manual_seed(seed)
    net = parsingNet(pretrained=False, backbone=cfg.backbone, cls_dim=(cells + 1, rows, cfg.num_lanes),
                     use_aux=cfg.use_aux)
    optimizer = get_optimizer(net, cfg)

    generator = torch.Generator().manual_seed(seed)
    probe = torch.randn(4, 3, 288, 800, generator=generator)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.reset_running_stats()
            m.momentum = None  # a cumulative average over the probe pass
    net.train()
    with torch.no_grad():
        net(probe)
        net.eval()
        hidden = net.cls[1](net.cls[0](net.pool(net.model(probe)[2]).view(-1, 1800)))
        part = hidden @ net.cls[2].weight.T
        net.cls[2].weight.mul_(IMAGE_PART / float(part.std()))
        net.cls[2].bias.copy_(torch.as_tensor(_bias(cells, rows), dtype=torch.float32))
        net.cls[2].bias.sub_(hidden.mean(0) @ net.cls[2].weight.T)  # the probe's mean logit at the pattern
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with _in_folder(out.parent):
        save_model(net, optimizer, 0, str(out.parent), False)  # writes ep000.pth
    saved = out.parent / "ep000.pth"
    if saved != out:
        saved.replace(out)
    state = torch.load(out, map_location="cpu")
    print(f"{out}: {len(state['model'])} tensors (seed {seed}, {backbone}, {dataset}: {cells} cells, {rows} rows); "
          f"bias range {float(np.min(_bias(cells, rows))):.1f}..{float(np.max(_bias(cells, rows))):.1f}")
    return out


class _in_folder:
    """chdir into a folder for a block (the official save_model asserts its folder exists; paths are absolute)."""

    def __init__(self, folder: Path) -> None:
        self.folder, self.before = Path(folder), None

    def __enter__(self):
        self.before = os.getcwd()
        os.chdir(self.folder)

    def __exit__(self, *exc):
        os.chdir(self.before)


def predict(repo: Path, ckpt: Path, data_root: Path, work: Path, out: Path, launch: Path | None,
            dataset: str) -> Path:
    config = DATASETS[dataset][0]
    work = Path(work).resolve()
    test_dir = work / "test"
    work.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(test_dir, ignore_errors=True)
    args = [str(repo / config), "--test_model", str(Path(ckpt).resolve()),
            "--data_root", str(Path(data_root).resolve()), "--test_work_dir", str(test_dir)]
    command = ([sys.executable, str(Path(launch).resolve()), str(repo), "test.py", *args] if launch else
               [sys.executable, "test.py", *args])
    env = dict(os.environ, ZOO_AUDIT=str(work / "load_audit.jsonl"))
    done = subprocess.run(command, cwd=str(repo), env=env)
    out = Path(out)
    if dataset == "tusimple":
        if done.returncode != 0:
            raise SystemExit(f"the official test.py failed (exit {done.returncode})")
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(test_dir / "tusimple_eval_tmp.txt", out)
    else:
        lines = test_dir / "culane_eval_tmp"
        if not lines.is_dir():
            raise SystemExit(f"the official test.py wrote no {lines} (exit {done.returncode})")
        if done.returncode != 0:
            print(f"the official test.py exited {done.returncode} after writing the .lines.txt files (its CULane "
                  f"scoring needs the compiled evaluation/culane/evaluate)")
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(lines, out)
    print(out)
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse(argv, __doc__, BACKBONES, "resnet18")
    if args.command == "checkpoint":
        make_checkpoint(args.repo, args.out, args.seed, args.backbone, args.dataset)
    else:
        predict(args.repo, args.ckpt, args.data_root, args.work, args.out, args.launch, args.dataset)
    return 0

if __name__ == "__main__":
    sys.exit(main())
