"""CLRNet's official side of the parity check (benchmarks/official_parity.py): run with the OFFICIAL environment's
python, never imported by the package (stdlib only at module level; the official modules are imported inside the
functions, from --repo).

    python clrnet.py checkpoint --repo REPO --out CKPT [--seed 0] [--backbone resnet18]
    python clrnet.py predict --repo REPO --ckpt CKPT --data-root DATA --work WORK --out PRED.json [--launch L.py]

``checkpoint`` builds the network with the official code (its Detector from configs/clrnet/clr_<backbone>_tusimple.py,
without ImageNet weights), wraps it as the official Runner does (MMDataParallel: ``module.`` keys) and saves it with
the official ``save_model`` (``{'net', 'optim', 'scheduler', 'recorder', 'epoch'}``), after setting values only
(never keys or shapes) so that random weights draw lanes that exercise the official decoding: five priors made
confident through ROIGather's per-prior output bias, their embeddings (and the ``priors`` buffers derived from them)
set to lines that run past the right edge, start right of it, start 3 px from the left edge, leave the image at the
left edge before their end and start above the bottom (extended down), with bent offsets and lengths that differ per
lane; and two less confident ones, beside a drawn lane (removed by the NMS) and a sixth (beyond max_lanes).

``predict`` writes a child config under WORK (``_base_`` the official TuSimple config, ``pretrained=False``, the
data root, no loader workers), runs the official test entry ``main.py CONFIG --test --load_from CKPT --gpus 0``
(through --launch's CPU stand-ins when given) in WORK (the official recorder copies the working directory's files
into its run folder and the CULane loader caches there: WORK holds a ``.gitignore`` that ignores everything, so
nothing is copied and nothing is written into the repository) and copies the ``tusimple_predictions.json`` it wrote
to --out. Its own TuSimple score runs after that file is written and may fail on random lanes (0 / 0): that is
ignored once the file exists.

The CULane release the same way, with ``--dataset culane``: ``checkpoint`` (the official clr_<backbone>_culane.py)
and ``predict`` on a CULane-layout DATA (``list/test.txt``,
an ``.lines.txt`` beside each image), which copies the tree of ``.lines.txt`` files the official test wrote
(clrnet/datasets/culane.py:114-128) to the folder --out.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from side_cli import parse  # noqa: E402

OFFICIAL = "Turoad/CLRNet@7269e9d1c1c650343b6c7febb8e764be538b1aed"
OURS = ["experiment=official_clrnet_tusimple", "backbone=resnet18"]
OURS_CULANE = ["experiment=official_clrnet_culane", "backbone=resnet18"]

BASE_CONFIG = "configs/clrnet/clr_{backbone}_{dataset}.py"
PREDICTIONS = "tusimple_predictions.json"  # clrnet/datasets/tusimple.py:94-96, in the run's work_dir
IGNORE_ALL = "*\n"  # WORK's .gitignore: the recorder copies nothing (recorder.py:51, 67-84)

# The drawn lanes: the prior whose values are set, its line [start_y (fraction of the height above the bottom row),
# start_x (fraction of W-1), theta (pi units)] (clr_head.py:125-139) and what it exercises. Lane k gets ROIGather's
# output bias SHIFT0 + SHIFT_STEP k (W is a grouped conv, one bias per prior: roi_gather.py:64-69, 132-134), which its
# near-identity fc layers carry to the logits (confident), to the length (LENGTH0 + LENGTH_STEP k of the strips) and
# to the bend of its offsets (BEND0 + BEND_STEP k of W-1 at the top row, growing with the square of the height).
LANES = (
    (100, [0.22, 0.45, 0.45]),   # starts above the bottom: extended down while inside
    (2, [0.10, 0.05, 0.60]),     # up to the left: leaves the image at the left edge before its end
    (70, [0.05, 0.004, 0.25]),   # starts 3 px from the left edge, up to the right: not extended down
    (175, [0.05, 1.02, 0.58]),   # starts right of the right edge, comes into the image
    (40, [0.00, 0.55, 0.18]),    # from the bottom up to the right, past the right edge in its upper part
)
# Two more, less confident (their shift given): one 16 px beside the first lane, which NMS removes, and a sixth
# lane, the least confident, which the kept number (max_lanes) leaves out.
EXTRA_LANES = (
    (101, [0.22, 0.47, 0.45], 2.75),
    (150, [0.00, 0.75, 0.50], 2.5),
)
SHIFT0, SHIFT_STEP = 3.0, 0.5
LENGTH0, LENGTH_STEP = 0.30, 0.15
BEND0, BEND_STEP = -0.03, 0.0175
ROI_MEAN = 0.4  # about the mean of a ReLU'd layer-normed feature (roi_gather.py:118)
LOGIT_OFFSET = 2.0  # positive - negative logit = mean feature - 2: ~0.17 for the undrawn priors, >= 0.8 drawn
JITTER = 0.02       # the official init's random offset weights, scaled: about 0.5 px of noise per row


def _official_imports(repo: str):
    """The official modules the checkpoint needs (the compiled lane NMS stubbed: building never calls it)."""
    import types

    sys.path.insert(0, os.path.abspath(repo))
    try:
        import clrnet.ops.nms_impl  # noqa: F401
    except ImportError:
        def no_nms(*args, **kwargs):
            raise RuntimeError("the lane NMS is not needed to build a checkpoint")

        stub = types.ModuleType("clrnet.ops.nms_impl")
        stub.nms_forward = no_nms
        sys.modules["clrnet.ops.nms_impl"] = stub
    from clrnet.engine.optimizer import build_optimizer
    from clrnet.engine.scheduler import build_scheduler
    from clrnet.models.registry import build_net
    from clrnet.utils.config import Config
    from clrnet.utils.net_utils import save_model
    from clrnet.utils.recorder import build_recorder
    from mmcv.parallel import MMDataParallel
    return Config, build_net, MMDataParallel, build_optimizer, build_scheduler, build_recorder, save_model


def _write_config(path: str, repo: str, backbone: str, dataset: str = "tusimple", data_root: str | None = None) -> str:
    """A child config of the official one: no ImageNet weights, the data root, no loader workers."""
    base = os.path.join(os.path.abspath(repo), BASE_CONFIG.format(backbone=backbone, dataset=dataset))
    lines = [f"_base_ = {base!r}", "backbone = dict(pretrained=False)", "workers = 0", "batch_size = 4"]
    if data_root:
        root = os.path.abspath(data_root)
        lines += [f"dataset_path = {root!r}", f"test_json_file = {os.path.join(root, 'test_label.json')!r}",
                  f"dataset = dict(val=dict(data_root={root!r}), test=dict(data_root={root!r}))"]
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path


def _work_folder(work: str) -> str:
    """WORK, made, with a .gitignore that ignores everything (the official recorder then copies nothing)."""
    os.makedirs(work, exist_ok=True)
    with open(os.path.join(work, ".gitignore"), "w") as f:
        f.write(IGNORE_ALL)
    return work


def _draw_lanes(net, seed: int) -> None:
    """Values only: the drawn priors' lines and confidence, lengths and bent offsets (see LANES)."""
    import torch

    torch.manual_seed(seed)
    head = net.heads
    dim = head.fc_hidden_dim
    rows = torch.linspace(0, 1, head.n_offsets)  # height above the bottom row of each offset's row
    with torch.no_grad():
        for modules in (head.cls_modules, head.reg_modules):  # Linear, ReLU pairs: near identity
            for layer in modules:
                if isinstance(layer, torch.nn.Linear):
                    layer.weight.copy_(torch.eye(dim) + 0.01 * torch.randn(dim, dim))
                    layer.bias.zero_()
        head.cls_layers.weight.zero_()
        head.cls_layers.weight[1] = 1.0 / dim
        head.cls_layers.bias.copy_(torch.tensor([0.0, -LOGIT_OFFSET]))
        reg = head.reg_layers
        reg.weight[:4].mul_(0.01)  # start_y, start_x, theta, length: the init's randomness, small
        reg.weight[4:].mul_(JITTER)
        reg.bias.zero_()
        # length and bend linear in the mean feature (shift + ROI_MEAN): LENGTH0 / BEND0 at SHIFT0
        length_slope = LENGTH_STEP / SHIFT_STEP
        reg.weight[3] += length_slope / dim
        reg.bias[3] = LENGTH0 - length_slope * (SHIFT0 + ROI_MEAN)
        bend_slope = BEND_STEP / SHIFT_STEP
        reg.weight[4:] += (bend_slope * rows ** 2)[:, None] / dim
        reg.bias[4:] = (BEND0 - bend_slope * (SHIFT0 + ROI_MEAN)) * rows ** 2
        head.roi_gather.W.weight.zero_()
        head.roi_gather.W.bias.zero_()
        drawn = [(index, line, SHIFT0 + SHIFT_STEP * k) for k, (index, line) in enumerate(LANES)]
        for index, line, shift in drawn + list(EXTRA_LANES):
            head.roi_gather.W.bias[index] = shift
            head.prior_embeddings.weight[index] = torch.tensor(line)
        # the buffers the eval forward reads, derived from the embeddings as a training forward leaves them
        priors, on_featmap = head.generate_priors_from_embeddings()
        head.priors.copy_(priors)
        head.priors_on_featmap.copy_(on_featmap)


def checkpoint(repo: str, out: str, seed: int = 0, backbone: str = "resnet18", dataset: str = "tusimple") -> str:
    """Build, set (values only) and save an official CLRNet file of `dataset`'s config; returns its path."""
    import tempfile

    import torch

    repo = os.path.abspath(repo)
    out = os.path.abspath(out)
    config, build_net, data_parallel, build_optimizer, build_scheduler, build_recorder, save_model = \
        _official_imports(repo)
    work = _work_folder(tempfile.mkdtemp(prefix="clrnet_ckpt_", dir=os.path.dirname(out) or "."))
    cfg = config.fromfile(_write_config(os.path.join(work, "config.py"), repo, backbone, dataset))
    cfg.gpus, cfg.seed, cfg.work_dirs = 1, seed, os.path.join(work, "work_dirs")
    torch.manual_seed(seed)
    here = os.getcwd()
    os.chdir(work)  # the recorder copies the working directory's files not ignored (recorder.py:51, 67-84)
    try:
        recorder = build_recorder(cfg)
    finally:
        os.chdir(here)
    net = data_parallel(build_net(cfg), device_ids=range(cfg.gpus))
    _draw_lanes(net.module, seed)
    optimizer = build_optimizer(cfg, net)
    scheduler = build_scheduler(cfg, optimizer)
    recorder.epoch = 69
    save_model(net, optimizer, scheduler, recorder)
    saved = os.path.join(recorder.work_dir, "ckpt", f"{recorder.epoch}.pth")
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    shutil.move(saved, out)
    shutil.rmtree(work, ignore_errors=True)
    return out


def predict(repo: str, ckpt: str, data_root: str, work: str, out: str, launch: str | None = None,
            backbone: str = "resnet18", dataset: str = "tusimple") -> str:
    """Run the official test entry on data_root with ckpt; copy its TuSimple prediction file (CULane: the folder
    of its .lines.txt files) to out."""
    repo, work = os.path.abspath(repo), _work_folder(os.path.abspath(work))
    config = _write_config(os.path.join(work, f"clrnet_test_{dataset}.py"), repo, backbone, dataset, data_root)
    work_dirs = os.path.join(work, "work_dirs")
    args = [config, "--test", "--load_from", os.path.abspath(ckpt), "--gpus", "0", "--work_dirs", work_dirs]
    command = [sys.executable, os.path.abspath(launch), repo, "main.py", *args] if launch \
        else [sys.executable, os.path.join(repo, "main.py"), *args]
    env = dict(os.environ, ZOO_AUDIT=os.path.join(work, "load_audit.jsonl"))
    # the CULane loader caches its list in cache/culane_<split>.pkl under the working directory and reads it back
    # whatever the data root (datasets/culane.py:41-59): never an earlier run's
    shutil.rmtree(os.path.join(work, "cache"), ignore_errors=True)
    before = set(glob.glob(os.path.join(work_dirs, "*")))
    result = subprocess.run(command, cwd=work, env=env)
    runs = sorted(set(glob.glob(os.path.join(work_dirs, "*"))) - before, key=os.path.getmtime)
    if dataset == "tusimple":
        written = [path for path in (os.path.join(run, PREDICTIONS) for run in runs) if os.path.exists(path)]
    else:
        written = [run for run in runs if glob.glob(os.path.join(run, "**", "*.lines.txt"), recursive=True)]
    if not written:
        raise SystemExit(f"the official test (exit {result.returncode}) wrote no predictions under {work_dirs}")
    if result.returncode:
        print(f"the official test exited {result.returncode} after writing {written[-1]} (its own score)",
              file=sys.stderr)
    out = os.path.abspath(out)
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    if dataset == "tusimple":
        shutil.copyfile(written[-1], out)
    else:
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(written[-1], out, ignore=lambda folder, names: [
            n for n in names if not n.endswith(".lines.txt") and not os.path.isdir(os.path.join(folder, n))])
    _report_audit(env["ZOO_AUDIT"])
    return out


def _report_audit(audit: str) -> None:
    """The keys the official (non-strict) load ignored, if any (the launcher's audit)."""
    if not os.path.exists(audit):
        return
    with open(audit) as f:
        for line in f:
            record = json.loads(line)
            if record["unexpected"]:
                print(f"the official load ignored {len(record['unexpected'])} keys: {record['unexpected'][:3]}",
                      file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv, __doc__, ("resnet18", "resnet34", "resnet101", "dla34"), "resnet18")
    if args.command == "checkpoint":
        print(checkpoint(str(args.repo), str(args.out), args.seed, args.backbone, args.dataset))
    else:
        print(predict(str(args.repo), str(args.ckpt), str(args.data_root), str(args.work), str(args.out),
                      None if args.launch is None else str(args.launch), backbone=args.backbone,
                      dataset=args.dataset))
    return 0

if __name__ == "__main__":
    sys.exit(main())
