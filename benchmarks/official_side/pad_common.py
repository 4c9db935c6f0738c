"""What the pytorch-auto-drive families of the parity check (scnn.py, bezierlanenet.py) share: run with the
OFFICIAL code's python, never imported by the project's package (stdlib only at module level; the official modules
are imported inside the functions, from --repo).

- ``load_official(repo)``: puts the repository on sys.path and makes ``mmcv.ops`` importable. pytorch-auto-drive
  imports ``ModulatedDeformConv2d`` and ``modulated_deform_conv2d`` from ``mmcv.ops`` whenever ``utils.models`` is
  imported (``utils/models/common_models/plugins/feature_flip_fusion.py`` l. 3), a compiled extension the
  pure-Python mmcv lacks. Where it is missing, a stand-in holding mmcv's parameters (``weight`` (out, in / groups,
  kh, kw), ``bias`` (out), mmcv's init) and computing DCNv2 with ``torchvision.ops.deform_conv2d`` is installed:
  used only to build and calibrate a checkpoint here (the official test runs under the launcher's shims).
- ``test_data(data_root, work, dataset)``: the dataset folder the official classes read: the images and
  ``lists/test.txt`` naming them without their suffix (``utils/datasets/lane_as_segmentation.py`` l. 57-64 and
  83-107, ``lane_as_bezier.py`` l. 87-98 and 136-160: TuSimple ``<root>/clips/<name>.jpg``, the prediction's
  raw_file ``clips/<name>.jpg``; CULane ``<root>/<name>.jpg``, written to ``./output/<name>.lines.txt``).
- ``run_test(...)``: ``main_landet.py --test --config CONFIG --checkpoint CKPT --cfg-options ...`` run from WORK
  (the tester writes ``./output/<exp_name>.json`` or the ``.lines.txt`` files, ``utils/runners/lane_det_tester.py``
  l. 57-97), the config's ImageNet weights off (``model.backbone_cfg.pretrained=False``), the data root, 0 loader
  workers, batches of 1.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path

COMMIT = "137e63a9e6c3cd2cfeb15e101808478d7b25ddbd"  # voldemortX/pytorch-auto-drive


def load_official(repo: Path) -> None:
    """The official repository on sys.path, and ``mmcv.ops`` importable (a stand-in where mmcv has no ``_ext``)."""
    if str(repo) not in sys.path:
        sys.path.insert(0, str(repo))
    try:
        import mmcv.ops  # noqa: F401
    except (ImportError, ModuleNotFoundError):
        _install_dcn_stand_in()


def _install_dcn_stand_in() -> None:
    import torch
    from torch import nn
    from torchvision.ops import deform_conv2d

    def pair(v):
        return tuple(v) if isinstance(v, (tuple, list)) else (v, v)

    def modulated_deform_conv2d(x, offset, mask, weight, bias=None, stride=1, padding=0, dilation=1, groups=1,
                                deform_groups=1):
        """DCNv2: x sampled bilinearly (zero outside) at each tap shifted by (dy, dx) of ``offset``, times ``mask``,
        convolved with ``weight``, plus ``bias`` (torchvision's offset and mask layouts are mmcv's)."""
        x = x.type_as(offset)
        return deform_conv2d(x, offset, weight.type_as(x), None if bias is None else bias.type_as(x),
                             stride=pair(stride), padding=pair(padding), dilation=pair(dilation),
                             mask=mask.type_as(x))

    class ModulatedDeformConv2d(nn.Module):
        """mmcv's parameters and init: weight uniform in +-1 / sqrt(in x kh x kw), bias zero."""

        def __init__(self, in_channels, out_channels, kernel_size, stride=1, padding=0, dilation=1, groups=1,
                     deform_groups=1, bias=True, deformable_groups=None):
            super().__init__()
            self.in_channels, self.out_channels = in_channels, out_channels
            self.kernel_size, self.stride = pair(kernel_size), pair(stride)
            self.padding, self.dilation = pair(padding), pair(dilation)
            self.groups = groups
            self.deform_groups = deformable_groups if deformable_groups is not None else deform_groups
            self.transposed, self.output_padding = False, (0,)
            self.weight = nn.Parameter(torch.empty(out_channels, in_channels // groups, *self.kernel_size))
            if bias:
                self.bias = nn.Parameter(torch.empty(out_channels))
            else:
                self.register_parameter("bias", None)
            self.init_weights()

        def init_weights(self):
            bound = 1.0 / math.sqrt(self.in_channels * self.kernel_size[0] * self.kernel_size[1])
            self.weight.data.uniform_(-bound, bound)
            if self.bias is not None:
                self.bias.data.zero_()

        def forward(self, x, offset, mask):
            return modulated_deform_conv2d(x, offset, mask, self.weight, self.bias, self.stride, self.padding,
                                           self.dilation, self.groups, self.deform_groups)

    import mmcv

    ops = types.ModuleType("mmcv.ops")
    ops.ModulatedDeformConv2d = ModulatedDeformConv2d
    ops.modulated_deform_conv2d = modulated_deform_conv2d
    sys.modules["mmcv.ops"] = ops
    mmcv.ops = ops


def build_model(repo: Path, config: str):
    """The config's network, built by the official ``MODELS`` registry without ImageNet weights; and the config."""
    load_official(repo)
    from utils.args import read_config
    from utils.models import MODELS

    cfg = read_config(str(repo / config))
    cfg["model"]["backbone_cfg"]["pretrained"] = False
    return MODELS.from_dict(cfg["model"]), cfg


def road_probe(count: int, seed: int, size: tuple[int, int] = (360, 640)):
    """(count, 3, H, W) road-like inputs, normalised as the test transforms (ImageNet mean and std): a sky, a grey
    road with noise from a horizon at 0.35 H and four white lines converging on a vanishing point (calibration
    images for the random checkpoints: their features' statistics are those of the test images, not of noise)."""
    import numpy as np
    import torch

    rng = np.random.default_rng(seed)
    h, w = size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    images = []
    for _ in range(count):
        horizon, vanish = 0.35 * h, w / 2 + rng.uniform(-0.06, 0.06) * w
        image = np.empty((h, w, 3))
        image[:] = np.array([140, 170, 200]) / 255.0  # RGB
        road = ys >= horizon
        image[road] = 90 / 255.0 + rng.normal(0, 8 / 255.0, (int(road.sum()), 1))
        t = np.clip((ys - horizon) / (h - horizon), 0, 1)
        for bottom in (-0.2 * w, 0.26 * w, 0.74 * w, 1.2 * w):
            centre = vanish + (bottom + rng.uniform(-0.03, 0.03) * w - vanish) * t
            line = road & (np.abs(xs - centre) <= 1 + 6 * t)
            image[line] = 235 / 255.0
        images.append((image - np.array([0.485, 0.456, 0.406])) / np.array([0.229, 0.224, 0.225]))
    return torch.tensor(np.stack(images).transpose(0, 3, 1, 2), dtype=torch.float32)


def save(net, out: Path) -> Path:
    """The official training's save (utils/common.py l. 24-30: {'model', 'optimizer': None, 'lr_scheduler': None})."""
    from utils.common import save_checkpoint

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(net, None, None, filename=str(out))
    return out


def test_data(data_root: Path, work: Path, dataset: str = "tusimple") -> Path:
    """WORK/data, the folder the official dataset class reads: DATA's entries linked, and ``lists/test.txt`` naming
    the images without their suffix; TuSimple from DATA's test.txt (``clips/<name>.jpg`` lines; the class reads
    ``<root>/clips/<name>.jpg``), CULane from DATA's list/test.txt (``/<name>.jpg`` lines; ``<root>/<name>.jpg``)."""
    data_root, root = Path(data_root).resolve(), Path(work) / "data"
    shutil.rmtree(root, ignore_errors=True)
    (root / "lists").mkdir(parents=True)
    for entry in data_root.iterdir():
        if entry.name not in ("lists",):
            (root / entry.name).symlink_to(entry, target_is_directory=entry.is_dir())
    listing = data_root / ("test.txt" if dataset == "tusimple" else "list/test.txt")
    prefix = "clips/" if dataset == "tusimple" else "/"
    names = []
    for line in listing.read_text().splitlines():
        name = line.strip().split(" ")[0] if line.strip() else ""
        if name:
            name = name[len(prefix):] if name.startswith(prefix) else name
            names.append(name[:-len(".jpg")] if name.endswith(".jpg") else name)
    (root / "lists" / "test.txt").write_text("".join(name + "\n" for name in names))
    return root


def run_test(repo: Path, config: str, ckpt: Path, data_root: Path, work: Path, out: Path, launch: Path | None,
             exp_name: str, dataset: str = "tusimple") -> Path:
    """The official test entry on DATA with CKPT, run from WORK; what it wrote copied to OUT: TuSimple its
    ``output/<exp_name>.json``, CULane its ``output/`` tree of ``.lines.txt`` files (the folder OUT names; the
    CULane class writes ``./output/<name>.lines.txt``, lane_as_segmentation.py l. 100-107, lane_as_bezier.py
    l. 153-160)."""
    work = Path(work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    data = test_data(data_root, work, dataset)
    output = work / "output"  # the tester opens ./output/<exp_name>.json: the folder must exist
    shutil.rmtree(output, ignore_errors=True)
    output.mkdir()
    options = " ".join([
        "model.backbone_cfg.pretrained=False",
        f"dataset.root={data}",
        "test.workers=0",
        "test.batch_size=1",
        f"test.exp_name={exp_name}",
        f"test.save_dir={work / 'checkpoints'}",
    ])
    args = ["main_landet.py", "--test", "--config", str(repo / config), "--checkpoint", str(Path(ckpt).resolve()),
            "--cfg-options", options]
    command = ([sys.executable, str(Path(launch).resolve()), str(repo), *args] if launch else
               [sys.executable, str(repo / args[0]), *args[1:]])
    env = dict(os.environ, ZOO_AUDIT=str(work / "load_audit.jsonl"))
    done = subprocess.run(command, cwd=str(work), env=env)
    written = output / f"{exp_name}.json" if dataset == "tusimple" else output
    if done.returncode != 0 or not written.exists():
        raise SystemExit(f"the official main_landet.py --test failed (exit {done.returncode}, {written} "
                         f"{'written' if written.exists() else 'not written'})")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if dataset == "tusimple":
        shutil.copyfile(written, out)
    else:
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(written, out)
    print(out)
    return out
