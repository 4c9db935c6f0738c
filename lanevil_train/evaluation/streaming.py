"""Batched, streaming, resumable evaluation: one JSON line of scores per image, appended as produced.

Memory stays flat whatever the test-set size (nothing is accumulated but the output file), and a
rerun with the same output file skips every image it already lists.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset, Subset

from lanevil_train.data.datamodule import ProcessedDataset, collate_lanes
from lanevil_train.data.normalization import DEFAULT_NORMALIZATION, spec_normalization
from lanevil_train.data.resize import DEFAULT_RESIZE, spec_resize
from lanevil_train.evaluation.lane_records import lane_record
from lanevil_train.evaluation.prediction_files import prediction_fields
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.models.cuda_graphs import GraphedInference
from lanevil_train.models.detector import LaneDetector
from lanevil_train.progress import progress_counter
from lanevil_train.results_log import ResultsLog


def stream_evaluate(model: LaneDetector, dataset: Dataset, out_path: str | Path, label: dict,
                    batch_size: int = 8, num_workers: int = 0, progress: str = "auto",
                    keep_lanes: bool = True, cuda_graphs: bool = True, predictions: bool = False) -> Path:
    """Score every image of `dataset` not yet in `out_path`, appending one JSON line each.

    `label` (e.g. {"model": ..., "dataset": ...}) is copied into every line; `progress` is a
    lanevil_train.progress mode (auto, rich, tqdm, plain, none). On a GPU the network runs through CUDA graphs
    (models/cuda_graphs.py: the same kernels, launched at once; `cuda_graphs=False` for the eager forward).
    `predictions` keeps each image's predicted lanes at full resolution and its run time in its line, for the
    official prediction files (evaluation/prediction_files.py).
    """
    log = ResultsLog(out_path)
    done = log.resume()
    claim_results(log.path, run_identity(model, label), resuming=bool(done))
    todo = [i for i in range(len(dataset)) if dataset.item_key(i) not in done]
    processor = model.preprocessor.sample_processor()
    loader = DataLoader(ProcessedDataset(Subset(dataset, todo), processor), batch_size=batch_size,
                        shuffle=False, num_workers=num_workers, collate_fn=collate_lanes)
    bar = progress_counter(len(dataset), len(dataset) - len(todo), "evaluate", "img", progress)
    model.eval()
    device = next(model.parameters()).device
    forward = GraphedInference(model) if cuda_graphs else model
    with torch.inference_mode():
        for batch in loader:
            sizes = [(int(m["height"]), int(m["width"])) for m in batch["meta"]]
            images = batch["images"].to(device)
            start = time.perf_counter()
            preds = model.decode_lanes(forward(images), tuple(images.shape[-2:]), sizes)
            if images.is_cuda:
                torch.cuda.synchronize(device)
            run_time_ms = (time.perf_counter() - start) * 1000 / len(preds)
            log.append({**label, **lane_record(pred, gt, meta, keep_lanes, model.row_sampling, model.culane_rows),
                        **(prediction_fields(pred, meta, run_time_ms, model.row_sampling, model.culane_rows)
                           if predictions else {})}
                       for pred, gt, meta in zip(preds, batch["lanes"], batch["meta"]))
            bar.update(len(preds))
    bar.close()
    return log.path


def run_identity(model: LaneDetector, label: dict) -> dict:
    """What makes two evaluations the same: the label, the network's weights (a hash), input geometry and
    normalisation, resize filter, decoding."""
    weights = getattr(model, "weights_sha256", None)  # an ONNX model's: its file's hash (tasks/detector/export.py)
    if weights is None:
        digest = hashlib.sha256()
        for name, tensor in sorted(model.state_dict().items()):
            digest.update(name.encode())
            digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        weights = digest.hexdigest()
    spec = model.build_config or {}
    # the normalisation and resize filter only when not the default, so the identities written before they were
    # recorded still match
    normalize = spec_normalization(spec)
    resize = spec_resize(spec)
    return {**{k: str(v) for k, v in label.items()}, "weights_sha256": weights,
            "input_size": list(spec.get("input_size", [])), "crop_top": spec.get("crop_top", 0.0),
            **({"normalize": normalize} if normalize != DEFAULT_NORMALIZATION else {}),
            **({"resize": resize} if resize != DEFAULT_RESIZE else {}),
            **({"row_sampling": model.row_sampling} if model.row_sampling != "linear" else {}),
            **({"culane_rows": list(model.culane_rows)} if model.culane_rows is not None else {}),
            "decode": {k: v for k, v in sorted(model.decode_kwargs.items())}}


def claim_results(path: Path, identity: dict, resuming: bool) -> None:
    """Record which evaluation writes `path` (in <name>.run.json beside it), or check that a resumed file was
    written by this same evaluation: resuming another model's results would report them as this model's."""
    marker = path.with_name(f"{path.stem}.run.json")
    if resuming and marker.is_file():
        before = json.loads(marker.read_text(encoding="utf-8"))
        changed = sorted(k for k in set(before) | set(identity) if before.get(k) != identity.get(k))
        if changed:
            differences = "; ".join("other weights" if k == "weights_sha256" else
                                    f"{k} was {before.get(k)!r}, now {identity.get(k)!r}" for k in changed)
            raise ValueError(f"{path} holds results of another evaluation ({differences}); resuming would report "
                             f"them as this one's: write to another folder (task.out_dir) or delete {path}")
    atomic_write_text(marker, json.dumps(identity, indent=1) + "\n")
