"""task=export: a detector's network (LaneDetector.forward: backbone, neck, head; no NMS) as an ONNX model, and
the ONNX model back as a detector whose network runs in onnxruntime (task=evaluate task.onnx=model.onnx).

Decoding stays in Python (the family head's decode), so an ONNX model and its PyTorch checkpoint give the same
scores through the same code. The model's build config (family, backbone, input size, crop, input normalisation,
decoding) travels in the ONNX file's metadata, as it does in a Lightning checkpoint.

    python -m lanevil_train task=export ckpt_path=last.ckpt task.out=model.onnx
    python -m lanevil_train task=export model=clrnet task.out=clrnet.onnx        # random weights
    python -m lanevil_train task=evaluate task.onnx=model.onnx task.suite=synthetic
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from torch import nn

from lanevil_train.files.atomic import atomic_write_bytes
from lanevil_train.models.detector import LaneDetector
from lanevil_train.models.factory import DetectorSpec, create_detector
from lanevil_train.tasks.builders import build_model, checkpoint_model, model_config, output_dir

log = logging.getLogger(__name__)

METADATA_KEY = "lanevil_model"  # the build config, as JSON
OUTPUTS_KEY = "lanevil_outputs"  # the raw output names, in forward's order, as JSON
INPUT_NAME = "images"


def export_onnx(model: LaneDetector, path: str | Path, opset: int = 17, batch_size: int = 1) -> dict:
    """Write `model`'s forward as ONNX at `path` (atomically), with a dynamic batch axis; returns
    {"outputs": [names], "difference": {name: float}} from onnxruntime checked against PyTorch on random
    images (another batch size than the one traced, so the dynamic axis is checked too)."""
    import onnx

    model = model.eval().cpu()
    height, width = model.build_config["input_size"]
    images = torch.randn(batch_size, 3, height, width, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        names = list(model(images))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    axes = {INPUT_NAME: {0: "batch"}, **{name: {0: "batch"} for name in names}}
    exported = io.BytesIO()  # in memory: the metadata goes in before the one (atomic) write
    torch.onnx.export(model, (images,), exported, dynamo=False, opset_version=opset, input_names=[INPUT_NAME],
                      output_names=names, dynamic_axes=axes)
    graph = onnx.load_from_string(exported.getvalue())
    for key, value in ((METADATA_KEY, json.dumps(model.build_config)), (OUTPUTS_KEY, json.dumps(names))):
        entry = graph.metadata_props.add()
        entry.key, entry.value = key, value
    atomic_write_bytes(path, graph.SerializeToString())
    return {"outputs": names, "difference": compare_with_pytorch(model, path, batch_size + 1)}


def compare_with_pytorch(model: LaneDetector, path: Path, batch_size: int) -> dict[str, float]:
    """Each raw output's largest difference, onnxruntime against PyTorch on random images, relative to the
    output's scale: max |onnx - torch| / max(1, max |torch|) (outputs in pixels reach hundreds)."""
    height, width = model.build_config["input_size"]
    images = torch.randn(batch_size, 3, height, width, generator=torch.Generator().manual_seed(1))
    onnx_model = OnnxLaneDetector(path)
    with torch.no_grad():
        expected = model.eval()(images)
    got = onnx_model(images)
    return {name: float((got[name] - value.float()).abs().max() / max(1.0, float(value.abs().max())))
            for name, value in expected.items()}


class OnnxNetwork(nn.Module):
    """An ONNX model run by onnxruntime as the network part of a detector (images -> raw outputs)."""

    def __init__(self, path: str | Path, providers: list[str] | None = None):
        super().__init__()
        import onnxruntime

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"task.onnx={path}: no such file (write one with task=export)")
        try:
            self.session = onnxruntime.InferenceSession(str(path), providers=providers or _providers(onnxruntime))
        except Exception as error:  # onnxruntime's own exception types
            raise ValueError(f"task.onnx={path}: onnxruntime cannot load it ({error})") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        if METADATA_KEY not in meta or OUTPUTS_KEY not in meta:
            raise ValueError(f"task.onnx={path}: no {METADATA_KEY!r} metadata; expected an ONNX model written by "
                             f"task=export (it records the family, backbone, input size and decoding)")
        self.build_config = json.loads(meta[METADATA_KEY])
        self.output_names = json.loads(meta[OUTPUTS_KEY])
        self.sha256 = hashlib.sha256(path.read_bytes()).hexdigest()

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        outputs = self.session.run(self.output_names, {INPUT_NAME: images.detach().cpu().float().numpy()})
        return {name: torch.from_numpy(np.asarray(value)).to(images.device)
                for name, value in zip(self.output_names, outputs)}


def _providers(onnxruntime) -> list[str]:
    available = onnxruntime.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


class OnnxLaneDetector(LaneDetector):
    """A LaneDetector whose network is an ONNX model: predict_lanes, decoding and scoring are the PyTorch
    family head's (its parameters unused; its anchors and decoding options from the build config)."""

    def __init__(self, path: str | Path, providers: list[str] | None = None):
        network = OnnxNetwork(path, providers)
        built = create_detector(DetectorSpec.from_build_config(network.build_config))
        super().__init__(nn.Identity(), built.head, decode=built.decode_kwargs,
                         crop_top=network.build_config.get("crop_top", 0.0), row_sampling=built.row_sampling,
                         culane_rows=built.culane_rows)
        self.build_config = network.build_config
        self.network = network
        self.weights_sha256 = network.sha256  # what identifies the weights (tasks/streaming.run_identity)

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.network(images)


def export(cfg: DictConfig) -> float:
    """task=export: the checkpoint's network (ckpt_path), or the configured model with random weights, as ONNX at
    task.out (default <run dir>/model.onnx); the onnxruntime check's largest relative difference is logged and
    returned, and one above task.tolerance is an error."""
    if cfg.ckpt_path:
        model = checkpoint_model(cfg)
    else:
        torch.manual_seed(cfg.seed)
        model = build_model(model_config(cfg))
        log.info("no ckpt_path: exporting %s with random weights", model.build_config["model"]["name"])
    out = Path(cfg.task.out) if cfg.task.out else output_dir(cfg) / "model.onnx"
    report = export_onnx(model, out, opset=cfg.task.opset)
    worst = max(report["difference"].values())
    message = (f"wrote {out} ({os.path.getsize(out) / 1e6:.1f} MB; outputs {', '.join(report['outputs'])}); "
               f"onnxruntime vs PyTorch: largest relative difference {worst:.1e}")
    log.info(message)
    print(message)
    if worst > cfg.task.tolerance:
        raise ValueError(f"task=export: onnxruntime's outputs differ from PyTorch's by up to {worst:.2e} "
                         f"(> task.tolerance={cfg.task.tolerance}): {report['difference']}")
    return worst
