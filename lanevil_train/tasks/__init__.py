"""Tasks: one function each, a composed config in, results out. Only tasks/ and cli.py see Hydra."""

from __future__ import annotations

from omegaconf import DictConfig


def run_task(cfg: DictConfig) -> float | None:
    """Dispatch to the task named by cfg.task.name."""
    name = cfg.task.name
    if name == "train":
        from lanevil_train.tasks.train import train

        return train(cfg)
    if name == "evaluate":
        from lanevil_train.tasks.evaluate import evaluate

        return evaluate(cfg)
    if name == "cross_domain":
        from lanevil_train.tasks.evaluate import cross_domain

        return cross_domain(cfg)
    if name == "build":
        from lanevil_train.tasks.build import build

        return build(cfg)
    if name == "report":
        from lanevil_train.tasks.report import report

        return report(cfg)
    if name == "compare":
        from lanevil_train.tasks.compare import compare

        return compare(cfg)
    raise ValueError(f"task.name={name!r}: expected one of 'train', 'evaluate', 'cross_domain', 'build', 'report', "
                     f"'compare'")
