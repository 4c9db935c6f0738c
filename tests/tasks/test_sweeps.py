"""hparams_search/: the paper's AAM++ sensitivity grids and the Optuna search, composed and (slow) run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.types import RunMode

from tests.tasks.cli_helpers import REPO, TINY

# The paper's sensitivity table (AAM++ on LaneATT): each parameter's grid.
PAPER_GRIDS = {
    "aam_t_haa": ("defense.callback.t_haa", [0.2, 0.3, 0.4, 0.5, 0.6, 0.7]),
    "aam_t_laa": ("defense.callback.t_laa", [0.05, 0.1, 0.2, 0.3, 0.4, 0.5]),
    "aam_beta": ("defense.callback.beta", [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]),
}
AAM_KEYS = {"defense.callback.t_haa", "defense.callback.t_laa", "defense.callback.beta"}


def compose_root(overrides: list[str]):
    """The root config with `overrides`, hydra node included (as `python -m lanevil_train ... --cfg all`)."""
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
            return compose(config_name="config", overrides=overrides, return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()


def sweep_values(key: str, value: str) -> list:
    """The values Hydra's grammar reads from `key=value` (a comma list, choice(...), interval(...))."""
    override = OverridesParser.create().parse_overrides([f"{key}={value}"])[0]
    return list(override.sweep_iterator())


@pytest.mark.parametrize("name", sorted(PAPER_GRIDS))
def test_grid_sweep_is_the_papers_grid_over_aam_plus_plus(name):
    key, grid = PAPER_GRIDS[name]
    cfg = compose_root([f"hparams_search={name}"])
    assert cfg.hydra.mode == RunMode.MULTIRUN
    assert cfg.hydra.sweeper._target_.endswith("BasicSweeper")
    params = dict(cfg.hydra.sweeper.params)
    assert list(params) == [key]
    assert sweep_values(key, params[key]) == grid
    assert cfg.defense.name == "aam++" and cfg.defense.callback.mode == "aam++"
    assert cfg.task.name == "train" and cfg.task.suite == "synthetic"
    # the swept key exists in the composed defense (an override of a missing key would fail every job)
    node, leaf = key.rsplit(".", 1)
    assert leaf in cfg.defense.callback, node


@pytest.mark.parametrize("name,value", [(name, value) for name in sorted(PAPER_GRIDS)
                                         for value in PAPER_GRIDS[name][1]])
def test_every_grid_point_is_a_valid_aam_plus_plus_callback(name, value):
    """Each job of a grid sweep builds its callback first: a value the callback rejects fails that job."""
    from hydra.utils import instantiate

    key, _ = PAPER_GRIDS[name]
    cfg = compose_root([f"hparams_search={name}", f"{key}={value}"])
    callback = instantiate(cfg.defense.callback)
    assert getattr(callback, key.rsplit(".", 1)[1]) == value
    assert callback.mode == "aam++" and callback.layer == cfg.model.attention_layer


def test_grid_sweep_composes_after_an_experiment():
    """hparams_search sits after experiment in the defaults list: both apply, the sweep's defense wins."""
    cfg = compose_root(["hparams_search=aam_beta", "experiment=quickstart", "trainer=ddp_spawn"])
    assert cfg.defense.name == "aam++"
    assert list(cfg.data.input_size) == [112, 320] and cfg.trainer.max_steps == 1000  # quickstart's
    assert cfg.trainer.strategy == "ddp_spawn"
    assert cfg.hydra.runtime.choices["hparams_search"] == "aam_beta"


def test_without_hparams_search_a_run_is_a_single_undefended_run():
    cfg = compose_root([])
    assert cfg.hydra.mode is None or cfg.hydra.mode == RunMode.RUN
    assert not cfg.hydra.sweeper.get("params")
    assert cfg.defense.name == "none"
    assert cfg.hydra.runtime.choices["hparams_search"] is None


def test_optuna_search_maximises_over_the_three_aam_parameters():
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper.optuna_sweeper")
    from hydra_plugins.hydra_optuna_sweeper._impl import create_optuna_distribution_from_override

    cfg = compose_root(["hparams_search=aam_optuna", "seed=7"])
    sweeper = cfg.hydra.sweeper
    assert cfg.hydra.mode == RunMode.MULTIRUN
    assert sweeper._target_.endswith("OptunaSweeper")
    assert str(sweeper.direction) == "maximize"
    assert sweeper.sampler._target_ == "optuna.samplers.TPESampler" and sweeper.sampler.seed == 7
    assert sweeper.n_jobs == 1 and sweeper.n_trials >= 10
    assert set(sweeper.params) == AAM_KEYS
    assert cfg.defense.name == "aam++" and cfg.task.suite == "synthetic"

    parser = OverridesParser.create()
    dists = {key: create_optuna_distribution_from_override(parser.parse_overrides([f"{key}={value}"])[0])
             for key, value in sweeper.params.items()}
    t_haa, t_laa = dists["defense.callback.t_haa"], dists["defense.callback.t_laa"]
    assert (t_haa.low, t_haa.high) == (0.2, 0.7)  # the paper's T_HAA range
    assert (t_laa.low, t_laa.high) == (0.05, 0.5)  # the paper's T_LAA range
    assert list(dists["defense.callback.beta"].choices) == [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]


def run_multirun(args: list[str], sweep_dir: Path, timeout: int = 900) -> subprocess.CompletedProcess:
    """`python -m lanevil_train ARGS hydra.sweep.dir=SWEEP_DIR` (a multirun); raises with the output on failure."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "WANDB_MODE": "offline", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "lanevil_train", *args, f"hydra.sweep.dir={sweep_dir}"]
    proc = subprocess.run(cmd, cwd=sweep_dir.parent, env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed ({proc.returncode}):\n"
                             f"{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}")
    return proc


TINY_SUITE = [*TINY, "trainer.max_steps=2", "trainer.max_epochs=10", "trainer.limit_val_batches=1",
              "task.suite=synthetic", "task.cases=1", "task.illusions=[rail_shadow]", "task.severities=[3]"]


def job_overrides(job_dir: Path) -> dict[str, str]:
    """The key=value overrides a sweep job ran with (its .hydra/overrides.yaml)."""
    lines = yaml.safe_load((job_dir / ".hydra" / "overrides.yaml").read_text())
    return dict(line.split("=", 1) for line in lines)


def perturbed_accuracy(job_dir: Path) -> float:
    """A sweep job's Accuracy (%) over the suite's perturbed images (its robustness/test_scores.json)."""
    rows = json.loads((job_dir / "robustness" / "test_scores.json").read_text())
    (row,) = [r for r in rows if r["images_kind"] == "perturbed"]
    return float(row["Accuracy"])


@pytest.mark.slow
def test_grid_sweep_runs_one_job_per_value(tmp_path):
    sweep_dir = tmp_path / "sweep"
    run_multirun(["hparams_search=aam_beta", *TINY_SUITE, "defense.callback.beta=0.2,0.6"], sweep_dir)
    jobs = sorted(p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit())
    assert [p.name for p in jobs] == ["0", "1"]  # the command line's two values replaced the paper's six
    assert [job_overrides(p)["defense.callback.beta"] for p in jobs] == ["0.2", "0.6"]
    for job in jobs:
        assert (job / "checkpoints" / "last.ckpt").is_file()
        assert 0.0 <= perturbed_accuracy(job) <= 100.0  # each job scored its model on the suite
    assert (sweep_dir / "multirun.yaml").is_file()


@pytest.mark.slow
def test_optuna_search_runs_trials_and_names_the_best(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper.optuna_sweeper")
    sweep_dir = tmp_path / "optuna"
    run_multirun(["hparams_search=aam_optuna", *TINY_SUITE, "hydra.sweeper.n_trials=2"], sweep_dir)
    jobs = sorted(p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit())
    assert [p.name for p in jobs] == ["0", "1"]
    trials = [job_overrides(p) for p in jobs]
    for params in trials:
        assert AAM_KEYS <= set(params)
        assert 0.2 <= float(params["defense.callback.t_haa"]) <= 0.7  # interval(0.2, 0.7) of aam_optuna.yaml
        assert 0.05 <= float(params["defense.callback.t_laa"]) <= 0.5
        assert float(params["defense.callback.beta"]) in (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
    assert trials[0] != trials[1]
    result = yaml.safe_load((sweep_dir / "optimization_results.yaml").read_text())
    assert result["name"] == "optuna"
    assert 0.0 <= float(result["best_value"]) <= 100.0
    # each trial returned its perturbed Accuracy on the suite: the best is the highest, with its parameters
    perturbed = [perturbed_accuracy(p) for p in jobs]
    assert float(result["best_value"]) == pytest.approx(max(perturbed))
    best = {k: float(v) for k, v in result["best_params"].items()}
    assert set(best) == AAM_KEYS
    assert best in [{k: float(params[k]) for k in AAM_KEYS}
                    for params, acc in zip(trials, perturbed) if acc == pytest.approx(max(perturbed))]


def test_every_job_of_a_grid_is_listed_up_front():
    from lanevil_train.tasks.sweep_check import sweep_jobs

    cfg = compose_root(["hparams_search=aam_beta", "trainer.max_steps=1"])
    cfg.hydra.overrides.task = ["hparams_search=aam_beta", "data.batch_size=2,4"]
    jobs = sweep_jobs(cfg)
    assert len(jobs) == 12
    assert jobs[0] == ["defense.callback.beta=0.1", "hparams_search=aam_beta", "data.batch_size=2"]
    assert jobs[-1] == ["defense.callback.beta=0.6", "hparams_search=aam_beta", "data.batch_size=4"]
    assert sweep_jobs(compose_root(["hparams_search=aam_optuna"])) is None  # Optuna picks its jobs as it goes


def test_a_bad_value_in_a_later_job_stops_the_sweep_before_the_first_job(tmp_path):
    sweep_dir = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "lanevil_train", "-m", *TINY, "trainer.max_steps=1", "data.batch_size=2,-1",
           f"hydra.sweep.dir={sweep_dir}"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "WANDB_MODE": "offline", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1
    assert "ConfigError: sweep job 1 [" in proc.stderr and " data.batch_size=-1 " in proc.stderr
    assert "trainer.max_steps=1] has 1 problem:" in proc.stderr
    assert "data.batch_size: expected an integer >= 1, got -1" in proc.stderr
    assert "No job of the sweep was started." in proc.stderr
    assert not sweep_dir.exists()


def test_the_pat_alpha_sweep_is_the_papers_grid_and_every_point_a_valid_pat_plus_plus():
    from lanevil_train.tasks.vlm.builders import prompt_defense

    cfg = compose_root(["hparams_search=pat_alpha", "model=vlm/hf", "model.path=/models/some-vlm", "data=clips"])
    assert cfg.hydra.mode == RunMode.MULTIRUN
    params = dict(cfg.hydra.sweeper.params)
    assert list(params) == ["defense.alpha"]
    grid = sweep_values("defense.alpha", params["defense.alpha"])
    assert grid == [0.1, 0.2, 0.3, 0.4, 0.6, 0.8]
    assert cfg.defense.name == "pat++" and cfg.task.name == "train"
    for value in grid:
        point = compose_root(["hparams_search=pat_alpha", "model=vlm/hf", "model.path=/models/some-vlm",
                              "data=clips", f"defense.alpha={value}"])
        assert prompt_defense(point).alpha == value


def test_the_pat_prefix_length_sweep_gives_valid_pat_plus_plus_points():
    from lanevil_train.tasks.vlm.builders import prompt_defense

    cfg = compose_root(["hparams_search=pat_prefix_length", "model=vlm/hf", "model.path=/models/some-vlm",
                        "data=clips"])
    assert cfg.hydra.mode == RunMode.MULTIRUN and cfg.defense.name == "pat++"
    grid = sweep_values("defense.prefix_length", dict(cfg.hydra.sweeper.params)["defense.prefix_length"])
    assert grid == [5, 10, 20, 40]
    for value in grid:
        point = compose_root(["hparams_search=pat_prefix_length", "model=vlm/hf", "model.path=/models/some-vlm",
                              "data=clips", f"defense.prefix_length={value}"])
        assert prompt_defense(point).prefix_length == value
