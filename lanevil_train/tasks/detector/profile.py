"""task=profile: what a detector costs on this machine: parameters, FLOPs per image at its input size, latency and
images/s at batch 1 and batch N (forward only, and forward + decode), and peak memory, as a markdown table printed
and written to <out_dir>/profile.md with everything in profile.json. The measuring is models/profile.py's.

    python -m lanevil_train task=profile model=clrnet data.input_size=[320,800]    # a config, random weights
    python -m lanevil_train task=profile ckpt_path=last.ckpt                         # a checkpoint's network
    python -m lanevil_train task=profile experiment=official_clrnet_culane ckpt_path=culane_r18.pth
    python -m lanevil_train task=profile task.families=all                          # every family, its paper's setting
"""

from __future__ import annotations

import functools
import json
import logging
import os
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

import lanevil_train.conf
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.models.detector import LaneDetector
from lanevil_train.models.profile import FLOP_CONVENTION, FLOP_COUNTER, markdown_table, profile_network
from lanevil_train.sim import render_scene
from lanevil_train.tasks.builders import (
    build_model,
    checkpoint_model,
    inference_device,
    model_config,
    model_label,
    output_dir,
)

log = logging.getLogger(__name__)

CONF = Path(lanevil_train.conf.__file__).parent


def detector_families() -> list[str]:
    """The detector family configs: conf/model/*.yaml (the VLM backends are in conf/model/vlm/)."""
    return sorted(path.stem for path in (CONF / "model").glob("*.yaml"))


def acquire_model(cfg: DictConfig) -> LaneDetector:
    """The network to profile: ckpt_path's (ours, or an official repository's file under its experiment=official_*
    config), else the configured model (model=, backbone=, data.input_size=) with random weights."""
    if cfg.ckpt_path:
        return checkpoint_model(cfg)
    torch.manual_seed(cfg.seed)
    return build_model(model_config(cfg))


def family_config(cfg: DictConfig, family: str) -> DictConfig:
    """The config of `family` at its paper's setting (experiment=paper_<family>: backbone, input size, crop; only
    model=<family> when there is none), at task.input_size when that is set, with this run's seed."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    paper = (CONF / "experiment" / f"paper_{family}.yaml").is_file()
    overrides = [f"experiment=paper_{family}" if paper else f"model={family}", f"seed={cfg.seed}"]
    if cfg.task.get("input_size") is not None:
        height, width = cfg.task.input_size
        overrides.append(f"data.input_size=[{height},{width}]")
    if GlobalHydra.instance().is_initialized():  # inside the command line's (or a test's) Hydra
        return compose(config_name="config", overrides=overrides)
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@functools.lru_cache(maxsize=4)
def _scene(seed: int) -> np.ndarray:
    image = render_scene(seed, width=1280, height=720)["image"]
    image.flags.writeable = False  # shared by every family of a run
    return image


def road_image(model: LaneDetector, seed: int = 0) -> torch.Tensor:
    """A simulated 1280x720 road scene as the network's input: its sky cut, resized with its filter and normalised
    with its preset (the build config's), so that decoding works on a road and not on noise."""
    return torch.from_numpy(model.preprocessor.image(_scene(seed), color="rgb"))


def measure(cfg: DictConfig, model: LaneDetector, device: torch.device, settings: dict) -> dict:
    spec = model.build_config
    row = {"label": model_label(model), "family": spec["model"]["name"],
           "backbone": spec["backbone"]["name"], "checkpoint": cfg.get("ckpt_path")}
    row.update(profile_network(model, spec["input_size"], device, settings["batch_sizes"], settings["warmup"],
                               settings["runs"], image=road_image(model, cfg.seed)))
    return row


def run_settings(cfg: DictConfig, device: torch.device) -> dict:
    """The device and the timing settings: task.warmup and task.runs (null: 10 and 50 on a GPU, 2 and 5 on the
    CPU), batch 1 and task.batch_size."""
    cuda = device.type == "cuda"
    warmup = cfg.task.warmup if cfg.task.warmup is not None else (10 if cuda else 2)
    runs = cfg.task.runs if cfg.task.runs is not None else (50 if cuda else 5)
    return {"device": str(device), "warmup": int(warmup), "runs": int(runs),
            "batch_sizes": sorted({1, int(cfg.task.batch_size)}), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
            "load_average_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
            "flop_counter": FLOP_COUNTER, "flop_convention": FLOP_CONVENTION}


def profile(cfg: DictConfig) -> float:
    """task=profile: the table of one model (ckpt_path's, or the configured one) or, with task.families, of every
    family named (all: conf/model/*.yaml but the VLMs), each at its paper's setting; written to <out_dir>/profile.md
    and profile.json. Returns the first model's batch-1 forward images/s."""
    families = cfg.task.families
    if families is not None and cfg.ckpt_path:
        named = OmegaConf.to_container(families) if OmegaConf.is_list(families) else families
        raise ValueError(f"task.families={named}: profiles each family with random weights; drop it to profile "
                         f"ckpt_path={cfg.ckpt_path}")
    if families is None and cfg.task.get("input_size") is not None:
        raise ValueError("task.input_size: the input size of task.families' models; for one model set "
                         "data.input_size=[height,width] (a checkpoint's is its own)")
    device = inference_device(cfg)
    settings = run_settings(cfg, device)
    names = None if families is None else detector_families() if families == "all" else list(families)
    cudnn = torch.backends.cudnn.benchmark
    torch.backends.cudnn.benchmark = device.type == "cuda"  # the fastest kernels for each input shape
    rows = []
    try:
        if names is None:
            rows.append(measure(cfg, acquire_model(cfg), device, settings))
            log.info("profiled %s", rows[-1]["label"])
        for name in names or []:
            try:
                family_cfg = family_config(cfg, name)
                rows.append(measure(family_cfg, acquire_model(family_cfg), device, settings))
            except (RuntimeError, ValueError, TypeError) as error:  # one family failing leaves the others' rows
                log.error("task=profile: %s failed: %s", name, error)
                rows.append({"label": name, "family": name, "error": f"{type(error).__name__}: {error}"})
            log.info("profiled %s", rows[-1]["label"])
            if device.type == "cuda":
                torch.cuda.empty_cache()
    finally:
        torch.backends.cudnn.benchmark = cudnn
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    text = report_text(rows, settings)
    atomic_write_text(out / "profile.md", text)
    atomic_write_text(out / "profile.json", json.dumps({"settings": settings, "rows": rows}, indent=2) + "\n")
    print(text)
    log.info("wrote %s and %s", out / "profile.md", out / "profile.json")
    failed = [row["label"] for row in rows if "error" in row]
    if failed:
        raise RuntimeError(f"task=profile: {', '.join(failed)} could not be profiled (the others' rows are in "
                           f"{out / 'profile.md'}): " + "; ".join(r["error"] for r in rows if "error" in r))
    return rows[0]["batches"][0]["forward_fps"]


def report_text(rows: list[dict], settings: dict) -> str:
    """profile.md: the machine and the settings, the table, and what each figure is."""
    device = next((row["device"] for row in rows if "device" in row), settings["device"])
    load = settings["load_average_at_start"]
    busy = (f"; load average {load[0]:.1f} over {settings['cpu_count']} cores at the start"
            + (" (other processes were running)" if load[0] > 0.5 else "")) if load else ""
    memory = next((b["peak_memory_method"] for row in rows for b in row.get("batches", [])), "")
    notes = [f"- Device: {device}; torch {settings['torch']}{busy}.",
             f"- Latency: the median of {settings['runs']} timed runs after {settings['warmup']} warm-up runs "
             f"(torch.inference_mode{', torch.cuda.synchronize before each clock read' if 'cuda' in device else ''}); "
             f"img/s = batch / latency. Forward is the network (backbone, neck, head); forward + decode adds the "
             f"family's decoding to lanes in image pixels (NMS, lane assembly). The input is one simulated road "
             f"scene, preprocessed as the model's own data pipeline does, repeated to the batch.",
             f"- FLOPs: {FLOP_COUNTER}, per image at the input size: {FLOP_CONVENTION}.",
             f"- Peak memory: {memory}."]
    uncounted = [f"{row['label']}: {', '.join(row['uncounted'])}" for row in rows if row.get("uncounted")]
    if uncounted:
        notes.append("- \\* FLOPs leave out operations torch's counter has no formula for: " + "; ".join(uncounted)
                     + ".")
    return "# Profile\n\n" + markdown_table(rows) + "\n" + "\n".join(notes) + "\n"
