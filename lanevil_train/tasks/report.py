"""task=report: one table and one set of plots from several evaluation runs, without running a model."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from lanevil_train.tasks.builders import build_logger, output_dir
from lanevil_train.tasks.results import log_results, write_results


def results_files(runs: list[str]) -> list[Path]:
    """per_image.jsonl of each run directory (a multirun sweep directory contributes all its runs)."""
    files = []
    for run in map(Path, runs):
        if (run / "per_image.jsonl").is_file():
            files.append(run / "per_image.jsonl")
        else:
            found = sorted(run.glob("*/per_image.jsonl"))
            if not found:
                raise FileNotFoundError(f"task.runs: no per_image.jsonl in {run} or its subdirectories")
            files.extend(found)
    return files


def report(cfg: DictConfig) -> float:
    """Combine the runs' per-image results into the report in this run's directory."""
    if not cfg.task.runs:
        raise ValueError("task=report needs task.runs=[run_dir, ...] (directories holding per_image.jsonl)")
    summary = write_results(results_files(list(cfg.task.runs)), output_dir(cfg), baseline=cfg.task.baseline)
    log_results(build_logger(cfg), output_dir(cfg))
    return summary["Accuracy"]
