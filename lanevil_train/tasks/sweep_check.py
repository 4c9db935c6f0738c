"""Check every job of a multirun before the first one starts.

Each job's config is otherwise checked when that job starts (`run_task`), so a bad value in the fifth job of
`python -m lanevil_train -m data.batch_size=8,-1` or `hparams_search=aam_beta 'defense.callback.beta=0.5,2.0'`
would fail only after the first jobs trained. `CheckEveryJob` (a Hydra callback, registered in conf/config.yaml)
lists the jobs as Hydra's basic sweeper will, composes each and runs `check_config` on it. Sweepers that choose
their jobs as they go (Optuna) cannot be listed up front; their jobs are checked when they start.
"""

from __future__ import annotations

import logging
import sys

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from lanevil_train.tasks.config_check import ConfigError, check_config

log = logging.getLogger(__name__)


def sweep_jobs(config: DictConfig) -> list[list[str]] | None:
    """The override list of every job the basic sweeper will launch (its params, then the command line's);
    None for another sweeper."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    sweeper = config.hydra.sweeper
    if not str(sweeper.get("_target_", "")).endswith("BasicSweeper"):
        return None
    params = [f"{key}={value}" for key, value in (sweeper.get("params") or {}).items()]
    overrides = OverridesParser.create().parse_overrides(params + list(config.hydra.overrides.task))
    return [job for batch in BasicSweeper.split_arguments(overrides, None) for job in batch]


class CheckEveryJob(Callback):
    """Before a multirun starts: compose and check the config of each of its jobs (see the module docstring)."""

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        from hydra import compose

        jobs = sweep_jobs(config)
        if jobs is None:
            log.info("sweeper %s: each job's config is checked when the job starts", config.hydra.sweeper._target_)
            return
        for number, overrides in enumerate(jobs):
            job = compose(config_name=config.hydra.job.config_name, overrides=overrides)
            try:
                check_config(job, where=f"sweep job {number} [{' '.join(overrides)}]")
            except ConfigError as error:
                # Hydra turns a callback's exceptions into warnings and goes on; SystemExit is not an Exception
                print(f"{type(error).__name__}: {error}\nNo job of the sweep was started.", file=sys.stderr)
                raise SystemExit(1) from None
