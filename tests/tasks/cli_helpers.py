"""Run the CLI in a subprocess with a tiny configuration (small images, few scenes, few steps)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2

from lanevil_train.lanes import default_h_samples
from lanevil_train.sim import render_scene

REPO = Path(__file__).resolve().parents[2]

TINY = [
    "data.input_size=[64,160]",
    "data.batch_size=2",
    "data.train.num_scenes=6",
    "data.train.size=[90,160]",
    "data.val.num_scenes=2",
    "data.val.size=[90,160]",
    "data.test.num_scenes=4",
    "data.test.size=[90,160]",
    "trainer.accelerator=cpu",
    "progress=none",
    "trainer.log_every_n_steps=1",
]


def run_cli(args: list[str], run_dir: Path, timeout: int = 600,
            pythonpath: list[Path] = ()) -> subprocess.CompletedProcess:
    """`python -m lanevil_train ARGS hydra.run.dir=RUN_DIR`; raises with the output on failure."""
    path = os.pathsep.join(map(str, [REPO, *pythonpath]))
    env = {**os.environ, "PYTHONPATH": path, "WANDB_MODE": "offline", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "lanevil_train", *args, f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, cwd=run_dir.parent, env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n"
                             f"{proc.stderr[-6000:]}")
    return proc


def run_in_process(args: list[str], run_dir: Path):
    """What `python -m lanevil_train ARGS` runs, run in this process: the config composed and checked as the
    command line does it (output_dir=run_dir), then its task. For a test's later runs of a command whose first run
    went through the command line: they skip a new interpreter's start and imports (10-15 s a run here)."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict

    from lanevil_train.tasks import run_task

    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
            cfg = compose(config_name="config", overrides=[*args, f"output_dir={run_dir}"], return_hydra_config=True)
            # what the command line's run sees too: HydraConfig holds its overrides (task=compare passes them on
            # to each run), without output_dir, which the command line sets through hydra.run.dir instead
            cfg.hydra.overrides.task = [o for o in cfg.hydra.overrides.task if not o.startswith("output_dir=")]
            HydraConfig.instance().set_config(cfg)
            with open_dict(cfg):
                del cfg["hydra"]
            return run_task(cfg)
    finally:
        HydraConfig.instance().cfg = None
        GlobalHydra.instance().clear()


def composed(overrides: list[str]):
    """The config `python -m lanevil_train OVERRIDES` composes, composed in this process (Hydra initialised for it and
    cleared after, so it works whatever another test left initialised)."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
            return compose(config_name="config", overrides=overrides)
    finally:
        GlobalHydra.instance().clear()


def write_photo_dataset(root: Path, names: list[str]) -> list[dict]:
    """Simulated scenes saved as JPEG files at root/<name> (a stand-in for a folder of photos); their records."""
    records = []
    for i, name in enumerate(names):
        sample = render_scene(100 + i, width=320, height=180)
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), cv2.cvtColor(sample["image"], cv2.COLOR_RGB2BGR))
        records.append({"raw_file": name, "rel_path": name, "image_path": path, "lanes": sample["lanes"],
                        "h_samples": default_h_samples(180)})
    return records


def write_fake_run(path, model: str, original: float, perturbed: float):
    """Per-image results of one model (its per_image.jsonl, as task=evaluate writes them): 2 cases, each an original
    and a shadow + a vehicle variant."""
    path.mkdir(parents=True)
    lines = []
    for case in ("c1", "c2"):
        for illusion, category, severity, acc in ((None, None, 0, original), ("rail_shadow", "shadow", 3, perturbed),
                                                  ("vehicle", "traffic_obstruction", 3, perturbed)):
            lines.append({"model": model, "dataset": "sim", "key": f"{case}/{illusion}", "case_id": case,
                          "image": None, "illusion": illusion, "category": category, "severity": severity,
                          "accuracy": acc, "fp": 0.0, "fn": 0.0, "num_pred": 4, "num_gt": 4})
    (path / "per_image.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
