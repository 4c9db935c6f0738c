"""One report for a whole multirun: `python -m lanevil_train -m model=laneatt,ufld,clrnet,scnn` ends with the
jobs' scores side by side (one row per model in the clean table, and the Perturbed / Original / Gap tables when
the jobs scored an illusion suite) in <sweep dir>/report, as `task=report task.runs=[<sweep dir>]` would write;
jobs that differ by `seed` only are one model's seeds (seeds.md: mean ± std, gains with intervals).

A Hydra callback (registered in conf/config.yaml). No report is made when the jobs wrote no per-image results
(a sweep of `task=build`), or when two jobs share a model label on one dataset without differing seeds (a sweep
over the settings of one model: its rows would merge; give each job its own `task.label`, or use task=compare). A
report that cannot be made is logged, never failing the finished jobs.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from lanevil_train.tasks.report import RESULT_FILES, path_order, write_run_reports
from lanevil_train.tasks.seed_report import seed_runs

log = logging.getLogger(__name__)


class ReportSweep(Callback):
    """After a multirun: the report of every job's results in <sweep dir>/report."""

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        sweep = Path(config.hydra.sweep.dir)
        if not sweep.is_dir():
            return
        files = sorted((path for job in sweep.iterdir() if job.is_dir() and job.name != "report"
                        for name in RESULT_FILES for path in job.rglob(name)), key=path_order)
        seeded = {path for runs in seed_runs(files).values() for path in runs.values()}
        owner: dict[tuple, str] = {}  # (model, dataset) -> the job that scored it
        for path in (p for p in files if p not in seeded):
            job = path.relative_to(sweep).parts[0]
            label = _label(path)
            if owner.setdefault(label, job) != job:
                log.info("no combined report of %s: jobs %s and %s both scored %s on %s (give each job its own "
                         "task.label to compare them in one table)", sweep, owner[label], job, *label)
                return
        if not files:
            return
        try:
            write_run_reports(files, sweep / "report")
        except ValueError as error:  # results that do not fit one report (e.g. lanes and VLM answers)
            log.warning("no combined report of %s: %s", sweep, error)


def _label(path: Path) -> tuple:
    """(model, dataset) of a results file's first record."""
    with open(path, encoding="utf-8") as handle:
        try:
            record = json.loads(handle.readline())
        except ValueError:
            return (None, str(path))
    return record.get("model"), record.get("dataset")
