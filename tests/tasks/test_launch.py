"""tasks/launch.py and conf/hydra/launcher/: training runs as jobs of the Hydra launcher the user picked."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from lanevil_train.tasks.launch import (
    JobOutcome,
    _Died,
    _outcome,
    _report_dead_jobs,
    _ReportingJob,
    launch_jobs,
    launcher_name,
    uses_job_launcher,
)

# task=build of one simulated case, one illusion at one severity, on 90x160 images: 2 images a job
BUILD = ["task=build", "task.illusions=[rail_shadow]", "task.severities=[1]", "data.test.size=[90,160]",
         "task.workers=0", "progress=none"]


@pytest.fixture()
def hydra_run():
    """A function that composes the root config (hydra node included) with overrides and makes it the current
    Hydra run, as `python -m lanevil_train OVERRIDES` would; the run is cleared afterwards."""
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        def start(overrides: list[str]):
            cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
            HydraConfig.instance().set_config(cfg)
            return cfg

        try:
            yield start
        finally:
            HydraConfig.instance().cfg = None
    GlobalHydra.instance().clear()


def test_slurm_launcher_config_extends_the_plugins_and_resolves(hydra_run):
    cfg = hydra_run(["hydra/launcher=slurm", "hydra.launcher.partition=gpu", "hydra.launcher.gpus_per_node=4",
                     "hydra.launcher.nodes=2", "hydra.launcher.account=lane", "hydra.sweep.dir=/scratch/sweep",
                     "trainer.devices=${hydra:launcher.gpus_per_node}", "+trainer.num_nodes=${hydra:launcher.nodes}"])
    launcher = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
    assert launcher["_target_"] == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert launcher["partition"] == "gpu" and launcher["account"] == "lane" and launcher["qos"] is None
    assert launcher["gpus_per_node"] == 4 and launcher["tasks_per_node"] == 4  # one task per GPU, interpolated
    assert launcher["nodes"] == 2 and launcher["cpus_per_task"] == 8 and launcher["mem_gb"] == 64
    assert launcher["timeout_min"] == 240 and launcher["array_parallelism"] == 64
    assert launcher["additional_parameters"] == {}
    assert launcher["submitit_folder"] == "/scratch/sweep/.submitit/%j"
    assert launcher["max_num_timeout"] == 0  # a field of the plugin's own config, kept by the extension
    assert cfg.trainer.devices == 4 and cfg.trainer.num_nodes == 2  # the trainer follows the job's resources
    assert launcher_name().endswith("SlurmLauncher") and uses_job_launcher()


def test_local_launcher_config_and_when_jobs_are_asked_for(hydra_run):
    cfg = hydra_run(["hydra/launcher=local", "hydra.launcher.gpus_per_node=2"])
    launcher = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
    assert launcher["_target_"].endswith("submitit_launcher.LocalLauncher")
    assert (launcher["gpus_per_node"], launcher["tasks_per_node"], launcher["timeout_min"]) == (2, 1, 240)
    assert uses_job_launcher()
    hydra_run(["hydra/launcher=submitit_local"])  # the plugin's own name works as well
    assert uses_job_launcher()
    hydra_run([])  # Hydra's BasicLauncher: the trainings run in this process
    assert launcher_name().endswith("BasicLauncher") and not uses_job_launcher()
    hydra_run(["hydra/launcher=local", "hydra.job.num=3"])  # a launched job (or a sweep's) launches nothing
    assert not uses_job_launcher()
    hydra_run(["hydra/launcher=local", "hparams_search=aam_beta"])  # a multirun: the sweep makes the jobs
    assert not uses_job_launcher()


def test_jobs_run_through_submitit_local_and_a_failing_one_is_reported(hydra_run, tmp_path):
    hydra_run(["hydra/launcher=local", "hydra.launcher.gpus_per_node=2", "hydra.launcher.timeout_min=10"])
    jobs = {"one": [*BUILD, "task.cases=1"],
            "aam++@1": [*BUILD, "task.cases=${hydra:launcher.gpus_per_node}"],  # resolved inside the job: 2
            "bad": [*BUILD, "task.cases=-1"]}
    outcomes = launch_jobs(jobs, tmp_path / "sweep")
    assert [o.name for o in outcomes] == list(jobs)
    assert all(isinstance(o, JobOutcome) for o in outcomes)
    one, two, bad = outcomes
    assert one.ok and two.ok and (one.error, two.error) == (None, None), (one.error, two.error)
    assert [o.overrides for o in outcomes] == list(jobs.values())  # as given, the interpolation unresolved
    for outcome, cases in ((one, 1), (two, 2)):
        root = tmp_path / "sweep" / outcome.name / "illusion_set"  # the job's output_dir is sweep/<name>
        manifest = [json.loads(line) for line in (root / "manifest.jsonl").read_text().splitlines()]
        assert len(manifest) == 2 * cases  # each case: its original and rail_shadow at severity 1
        assert outcome.log == str(tmp_path / "sweep" / outcome.name / "app.log")
    assert not bad.ok and bad.value is None
    assert "task.cases" in bad.error and "-1" in bad.error and "ConfigError" in bad.error
    assert bad.log == str(tmp_path / "sweep" / "bad" / "app.log") and Path(bad.log).is_file()
    assert "task.cases" in Path(bad.log).read_text()  # the traceback is in the job's log as well
    assert not (tmp_path / "sweep" / "bad" / "illusion_set").exists()
    assert len(list((tmp_path / "sweep" / ".submitit").glob("*/*_result.pkl"))) == 3  # one submitit job each


def test_bad_jobs_are_refused_before_anything_is_launched(hydra_run, tmp_path):
    hydra_run(["hydra/launcher=local"])
    with pytest.raises(ValueError, match=r"jobs\['x'\].*do not compose"):
        launch_jobs({"ok": BUILD, "x": ["model=no_such_model"]}, tmp_path / "sweep")
    with pytest.raises(ValueError, match="job name '../up'"):
        launch_jobs({"../up": BUILD}, tmp_path / "sweep")
    with pytest.raises(ValueError, match="expected a list of override strings"):
        launch_jobs({"a": "task=build"}, tmp_path / "sweep")
    with pytest.raises(ValueError, match="non-empty dict"):
        launch_jobs({}, tmp_path / "sweep")
    with pytest.raises(ValueError, match="sweep_dir"):
        launch_jobs({"a": BUILD}, tmp_path / "it's")
    assert not (tmp_path / "sweep").exists()


class _DeadJob:
    """A stand-in for a submitit job killed before writing its result."""

    class paths:
        stderr = Path("/sweep/.submitit/77/77_0_log.err")

    def results(self):
        from submitit.core.utils import UncompletedJobError

        raise UncompletedJobError("Job 77 (task: 0) has not produced any output (state: INTERRUPTED)\n"
                                  "Error stream produced:\nslurmstepd: error: Detected 1 oom-kill event(s)")


def test_a_dead_submitit_job_comes_back_as_died_and_the_patch_is_undone(tmp_path):
    import submitit
    from hydra.core.utils import JobReturn, JobStatus

    died = _ReportingJob(_DeadJob()).results()
    assert len(died) == 1 and isinstance(died[0], _Died)
    assert died[0].log == "/sweep/.submitit/77/77_0_log.err"
    assert "INTERRUPTED" in died[0].error and died[0].error.endswith("oom-kill event(s)")
    outcome = _outcome("aam++@2", ["seed=2"], died[0], tmp_path)
    assert (outcome.name, outcome.overrides, outcome.ok, outcome.value) == ("aam++@2", ["seed=2"], False, None)
    assert (outcome.error, outcome.log) == (died[0].error, died[0].log)
    failed = JobReturn(status=JobStatus.FAILED, _return_value=RuntimeError("raised outside the task"))
    (tmp_path / "cli.log").write_text("log\n")
    outcome = _outcome("x", [], failed, tmp_path)  # a launcher's failed JobReturn (not our task's outcome)
    assert not outcome.ok and outcome.error == "RuntimeError: raised outside the task"
    assert outcome.log == str(tmp_path / "cli.log")
    original = submitit.AutoExecutor
    with _report_dead_jobs():
        assert submitit.AutoExecutor is not original and issubclass(submitit.AutoExecutor, original)
    assert submitit.AutoExecutor is original
    with pytest.raises(KeyError), _report_dead_jobs():
        raise KeyError("launch failed")
    assert submitit.AutoExecutor is original  # restored even when the launch raises
