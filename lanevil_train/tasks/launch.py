"""Run training jobs through the Hydra launcher the user picked (`hydra/launcher=slurm`, `submitit_local`, ...).

A task that runs several trainings (task=compare) calls launch_jobs when uses_job_launcher() says the user asked
for jobs: each run is then one job of that launcher (one SLURM job, or one local process), composed from the app's
config with the run's overrides plus this run's hydra overrides, written to <sweep_dir>/<name>/, and this process
waits for all of them. A job that fails (its task raises, or it dies: killed, timed out, out of memory) comes back
as a failed JobOutcome naming its error and log; it never stops the waiting for the others. docs/cluster.md.
"""

from __future__ import annotations

import logging
import re
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from lanevil_train.tasks import run_task

log = logging.getLogger(__name__)

BASIC_LAUNCHER = "hydra._internal.core_plugins.basic_launcher.BasicLauncher"
SUBMITIT_MODULE = "hydra_plugins.hydra_submitit_launcher"
ERROR_LINES = 12  # the last lines of a dead job's error (submitit's message and error stream) kept in its outcome
_NAME = re.compile(r"[A-Za-z0-9_+@=-][A-Za-z0-9_.+@=-]*")
_UNQUOTABLE = set("'\"\\$")  # characters a Hydra override's quoted value would read as escapes or interpolations


@dataclass
class JobOutcome:
    """One launched job: its name and overrides, whether its task finished, what it returned, else its error
    (the traceback's last lines), and where its log is."""

    name: str
    overrides: list[str]
    ok: bool
    value: object
    error: str | None
    log: str | None


@dataclass
class _Died:
    """What a submitit job that ended without a result (killed, timed out, out of memory) comes back as."""

    error: str
    log: str | None


def launcher_name() -> str:
    """The `_target_` of the current Hydra run's launcher (hydra.launcher), e.g. ...submitit_launcher.SlurmLauncher."""
    from hydra.core.hydra_config import HydraConfig

    return str(HydraConfig.get().launcher._target_)


def uses_job_launcher() -> bool:
    """True when this is a single run (no -m, not itself a launched job) whose launcher is not Hydra's
    BasicLauncher: the user asked for `hydra/launcher=...`, so its trainings should run as jobs."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hydra = HydraConfig.get()
    if hydra.mode == RunMode.MULTIRUN or not OmegaConf.is_missing(hydra.job, "num"):
        return False  # a sweep, or a job of one: launchers number their jobs (hydra.job.num)
    return launcher_name() != BASIC_LAUNCHER


def launch_jobs(jobs: dict[str, list[str]], sweep_dir: Path) -> list[JobOutcome]:
    """Run every job (name -> overrides) through the current run's launcher, each in sweep_dir/<name>; wait for all
    of them and return one outcome per job, in the order given. Jobs that fail or die are failed outcomes, not
    errors; overrides that do not compose raise ValueError before anything is launched."""
    from hydra._internal.callbacks import Callbacks
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.plugins import Plugins
    from hydra.types import HydraContext

    names = _check_jobs(jobs)
    sweep_dir = _check_sweep_dir(sweep_dir)
    master = _master_config(sweep_dir)
    loader = GlobalHydra.instance().config_loader()
    job_overrides = [[*map(str, jobs[name]), f"hydra.sweep.dir='{sweep_dir}'", f"hydra.sweep.subdir='{name}'"]
                     for name in names]
    for name, overrides in zip(names, job_overrides):
        try:  # every job's config composes here, or nothing is launched
            loader.load_sweep_config(master, list(overrides))
        except Exception as error:  # noqa: BLE001 -- Hydra's composition errors have several types
            raise ValueError(f"jobs[{name!r}]: the overrides {jobs[name]} do not compose: {error}") from None
    context = HydraContext(config_loader=loader, callbacks=Callbacks())  # no CheckEveryJob / ReportSweep
    launcher = Plugins.instance().instantiate_launcher(hydra_context=context, task_function=run_launched_job,
                                                       config=master)
    log.info("launching %d jobs with %s into %s", len(names), type(launcher).__name__, sweep_dir)
    patch = _report_dead_jobs if type(launcher).__module__.startswith(SUBMITIT_MODULE) else _no_patch
    with patch():
        returns = list(launcher.launch(job_overrides, initial_job_idx=0))
    if len(returns) != len(names):
        raise RuntimeError(f"launcher {type(launcher).__name__} returned {len(returns)} results for {len(names)} jobs")
    outcomes = [_outcome(name, jobs[name], ret, sweep_dir / name) for name, ret in zip(names, returns)]
    for outcome in outcomes:
        if not outcome.ok:
            log.error("job %s failed (log: %s):\n%s", outcome.name, outcome.log, outcome.error)
    return outcomes


def run_launched_job(cfg: DictConfig) -> JobOutcome:
    """A launched job's task function (module level: submitit pickles it): run_task(cfg), with any exception turned
    into a failed outcome, so one job's error never makes the launcher stop waiting for the others."""
    from hydra.core.hydra_config import HydraConfig

    hydra = HydraConfig.get()
    name = str(hydra.sweep.subdir)
    overrides = [str(o) for o in OmegaConf.to_container(hydra.overrides.task, resolve=False)]  # as given
    log_file = Path(hydra.runtime.output_dir) / f"{hydra.job.name}.log"
    try:
        value = run_task(cfg)
    except Exception as error:
        log.exception("job %s failed", name)
        return JobOutcome(name, overrides, False, None, _error_text(error), _existing(log_file))
    return JobOutcome(name, overrides, True, value, None, _existing(log_file))


def _check_jobs(jobs: dict[str, list[str]]) -> list[str]:
    """The job names, checked: each a plain folder name with a list of override strings."""
    if not isinstance(jobs, dict) or not jobs:
        raise ValueError(f"jobs: expected a non-empty dict of job name -> override list, got {jobs!r}")
    for name, overrides in jobs.items():
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise ValueError(f"jobs: job name {name!r} must be a folder name of letters, digits and _ . + @ = - "
                             f"(not starting with '.')")
        if isinstance(overrides, str) or not all(isinstance(o, str) for o in overrides):
            raise ValueError(f"jobs[{name!r}]: expected a list of override strings, got {overrides!r}")
    return list(jobs)


def _check_sweep_dir(sweep_dir: Path) -> Path:
    """sweep_dir as an absolute path (jobs may start in another working directory) a Hydra override can carry."""
    path = Path(sweep_dir).absolute()
    bad = sorted(_UNQUOTABLE & set(str(path)))
    if bad:
        raise ValueError(f"sweep_dir: {path} contains {bad}; expected a path without quotes, backslashes or '$'")
    return path


def _master_config(sweep_dir: Path) -> DictConfig:
    """The current run's config with its hydra node (what the launcher is set up with), its sweep dir sweep_dir."""
    import copy

    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        raise ValueError("launch_jobs: no current Hydra run; call it from a task run by `python -m lanevil_train` "
                         "(or after HydraConfig.instance().set_config on a config composed with its hydra node)")
    hydra = HydraConfig.get()
    full = hydra._get_parent()  # the whole config: set_config keeps it as the hydra node's parent
    master = copy.deepcopy(full if full is not None and "hydra" in full else HydraConfig.instance().cfg)
    with read_write(master.hydra), open_dict(master.hydra):
        master.hydra.sweep.dir = str(sweep_dir)
    return master


def _outcome(name: str, overrides: list[str], ret: Any, job_dir: Path) -> JobOutcome:
    """A launcher's return for one job (a JobReturn, or _Died) as its JobOutcome."""
    from hydra.core.utils import JobStatus

    if isinstance(ret, _Died):
        return JobOutcome(name, list(overrides), False, None, ret.error, ret.log)
    if getattr(ret, "status", None) == JobStatus.COMPLETED and isinstance(ret.return_value, JobOutcome):
        outcome = ret.return_value
        if outcome.name != name:
            raise RuntimeError(f"launcher returned the outcome of job {outcome.name!r} in the place of {name!r}")
        return outcome
    error = getattr(ret, "_return_value", ret)  # a JobReturn of a failed job holds the exception
    logs = sorted(job_dir.glob("*.log"))  # the job's Hydra log, <job name>.log
    text = _error_text(error) if isinstance(error, BaseException) else f"launcher returned {error!r}"
    return JobOutcome(name, list(overrides), False, None, text, str(logs[0]) if logs else None)


@contextmanager
def _report_dead_jobs() -> Iterator[None]:
    """While a submitit launcher waits: a job that ended without a result (killed, timed out, out of memory) comes
    back as _Died instead of raising, which would stop the waiting at the first such job."""
    import submitit

    original = submitit.AutoExecutor

    class ReportingExecutor(original):  # type: ignore[misc, valid-type]
        """submitit's executor whose jobs report their death instead of raising it."""

        def map_array(self, fn, *iterables):
            return [_ReportingJob(job) for job in super().map_array(fn, *iterables)]

    submitit.AutoExecutor = ReportingExecutor
    try:
        yield
    finally:
        submitit.AutoExecutor = original


@contextmanager
def _no_patch() -> Iterator[None]:
    """Other launchers are used as they are."""
    yield


class _ReportingJob:
    """A submitit job whose results() returns [_Died] for a job without a result instead of raising."""

    def __init__(self, job: Any) -> None:
        self.job = job

    def results(self) -> list:
        """The job's results, or [_Died(its error, its error log)]."""
        try:
            return self.job.results()
        except Exception as error:  # noqa: BLE001 -- submitit raises UncompletedJobError / FailedJobError
            return [_Died(_last_lines(str(error)), str(self.job.paths.stderr))]

    def __getattr__(self, name: str) -> Any:
        return getattr(self.job, name)


def _error_text(error: BaseException) -> str:
    """The end of error's traceback: where it was raised (the last frame) and the whole exception message."""
    frames = traceback.format_tb(error.__traceback__)[-1:]
    return "".join([*frames, *traceback.format_exception_only(error)]).rstrip()


def _last_lines(text: str, count: int = ERROR_LINES) -> str:
    """The last `count` non-empty lines of text."""
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return "\n".join(lines[-count:])


def _existing(path: Path) -> str | None:
    """str(path) when the file is there (a job's Hydra log), else None."""
    return str(path) if path.is_file() else None
