"""task=compare: one run per defense under runs/, the gain report, resuming, and the report-only route."""

from __future__ import annotations

import json
import shutil

import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from lanevil_train.evaluation.lane_records import read_records
from lanevil_train.tasks.compare import check_defenses, compare, compose_run, run_overrides
from lanevil_train.tasks.finished_runs import records_from_runs
from tests.report.test_defenses import RECORDS
from tests.tasks.cli_helpers import TINY, run_cli, run_in_process

COMPARE = ["task=compare", "task.defenses=[none,aam++]", *TINY, "trainer.max_steps=2", "trainer.limit_val_batches=0",
           "task.cases=1", "task.illusions=[rail_shadow]", "task.severities=[3]"]


def _mtimes(run_dir) -> dict[str, int]:
    """Modification times of a run's checkpoints and done marker."""
    files = sorted(run_dir.glob("checkpoints/*.ckpt")) + sorted(run_dir.glob("robustness/done.json"))
    return {str(p.relative_to(run_dir)): p.stat().st_mtime_ns for p in files}


def test_compare_trains_each_defense_reports_gains_and_resumes(tmp_path, capsys, caplog):
    out = tmp_path / "compare"
    proc = run_cli(COMPARE, out)
    for defense, label in (("none", "laneatt-resnet18"), ("aam++", "laneatt-resnet18+aam++")):
        run = out / "runs" / defense
        assert (run / "checkpoints" / "last.ckpt").is_file()
        assert OmegaConf.load(run / "config.yaml").defense.name == defense
        records = read_records(run / "robustness" / "per_image.jsonl")
        assert sorted((r["severity"], r["illusion"]) for r in records) == [(0, None), (3, "rail_shadow")]
        assert {r["model"] for r in records} == {label}
        assert json.loads((run / "robustness" / "done.json").read_text())["defense"] == defense
    gains = json.loads((out / "defense_gain.json").read_text())
    assert [(r["defense"], r["category"]) for r in gains] == [("aam++", "shadow"), ("aam++", "average"),
                                                               ("aam++", "original")]
    scores = {r["defense"]: r for r in json.loads((out / "defense_scores.json").read_text())}
    assert list(scores) == ["none", "aam++"]
    shadow = gains[0]
    expected = scores["aam++"]["shadow/Accuracy"] - scores["none"]["shadow/Accuracy"]
    assert shadow["Accuracy/gain"] == pytest.approx(expected)
    assert (out / "defense_gain.png").stat().st_size > 2000
    assert "defense_gain.png" in (out / "compare.md").read_text()
    assert "Accuracy gain over none" in proc.stdout

    # the same command again: both runs are finished, nothing is trained or scored
    before = {d: _mtimes(out / "runs" / d) for d in ("none", "aam++")}
    capsys.readouterr()
    caplog.clear()
    with caplog.at_level("INFO"):
        run_in_process(COMPARE, out)  # the later runs in this process (the first went through the command line)
    logs = "".join(capsys.readouterr()) + caplog.text
    assert logs.count("already done") == 2
    assert {d: _mtimes(out / "runs" / d) for d in ("none", "aam++")} == before

    # interrupted while scoring aam++: only its robustness part is redone, from its checkpoint
    shutil.rmtree(out / "runs" / "aam++" / "robustness")
    caplog.clear()
    with caplog.at_level("INFO"):
        run_in_process(COMPARE, out)
    logs = "".join(capsys.readouterr()) + caplog.text
    assert "defense=none already done" in logs and "defense=aam++ resuming from" in logs
    assert _mtimes(out / "runs" / "none") == before["none"]
    assert {k: v for k, v in _mtimes(out / "runs" / "aam++").items() if k.startswith("checkpoints")} == \
        {k: v for k, v in before["aam++"].items() if k.startswith("checkpoints")}
    assert len(read_records(out / "runs" / "aam++" / "robustness" / "per_image.jsonl")) == 2
    assert (out / "runs" / "aam++" / "robustness" / "done.json").is_file()


def test_defenses_are_checked_up_front():
    assert check_defenses(["none", "aam++", "pgd"]) == ["none", "aam++", "pgd"]
    with pytest.raises(ValueError, match=r"unknown defense\(s\) \['aam\+'\].*'aam\+\+'"):
        check_defenses(["none", "aam+"])
    with pytest.raises(ValueError, match="must include 'none'"):
        check_defenses(["aam", "aam++"])
    with pytest.raises(ValueError, match="listed more than once"):
        check_defenses(["none", "aam", "aam"])
    with pytest.raises(ValueError, match="at least one defense"):
        check_defenses(["none"])


def test_each_run_gets_the_users_overrides_but_its_own_task_defense_and_directory(tmp_path):
    user = ["task=compare", "task.defenses=[none,pgd]", "defense=aam", "experiment=quickstart", "seed=3",
            "trainer.max_steps=7", "output_dir=/elsewhere"]
    assert run_overrides(user) == ["experiment=quickstart", "seed=3", "trainer.max_steps=7"]
    with pytest.raises(ValueError, match="defense.callback.beta=0.3.*would apply to every defense"):
        run_overrides(["defense.callback.beta=0.3"])
    with pytest.raises(ValueError, match="ckpt_path=x.ckpt"):
        run_overrides(["ckpt_path=x.ckpt"])
    (tmp_path / "pgd" / "checkpoints").mkdir(parents=True)
    (tmp_path / "pgd" / "checkpoints" / "last.ckpt").write_bytes(b"")
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
            cfg = compose(config_name="config", overrides=["task=compare", "task.cases=2", "task.severities=[4]"])
            none = compose_run(cfg, "none", run_overrides(user), tmp_path / "none")
            pgd = compose_run(cfg, "pgd", run_overrides(user), tmp_path / "pgd")
    finally:
        GlobalHydra.instance().clear()
    for run, defense in ((none, "none"), (pgd, "pgd")):
        assert run.task.name == "train" and run.defense.name == defense
        assert run.task.suite == "synthetic" and run.task.cases == 2 and list(run.task.severities) == [4]
        assert run.seed == 3 and run.trainer.max_steps == 7 and list(run.data.input_size) == [112, 320]
    assert none.output_dir == str(tmp_path / "none") and none.ckpt_path is None
    assert pgd.output_dir == str(tmp_path / "pgd")
    assert pgd.ckpt_path == str(tmp_path / "pgd" / "checkpoints" / "last.ckpt")
    assert pgd.logger.save_dir == str(tmp_path / "pgd")  # interpolations follow the run directory


def _write_run(run_dir, records, defense=None, seed=None):
    (run_dir / "robustness").mkdir(parents=True)
    lines = [json.dumps({**r, "key": f"{r['case_id']}/{r.get('illusion')}"}) + "\n" for r in records]
    (run_dir / "robustness" / "per_image.jsonl").write_text("".join(lines))
    if defense:
        (run_dir / ".hydra").mkdir()
        config = {"defense": {"name": defense}, **({"seed": seed} if seed is not None else {})}
        OmegaConf.save(OmegaConf.create(config), run_dir / ".hydra" / "config.yaml")


def _shifted(records, shift):
    """The records with every perturbed accuracy moved by `shift` (clean ones unchanged)."""
    return [{**r, "accuracy": r["accuracy"] + shift if r["severity"] else r["accuracy"]} for r in records]


def test_report_only_over_seeds_gives_mean_std_and_intervals(tmp_path):
    # a multirun over defense and seed: none at its records on seeds 0, 1, 2; aam++ +10 points +-1 on each
    sweep = tmp_path / "multirun"
    for job, (defense, seed) in enumerate((d, s) for d in ("none", "aam++") for s in (0, 1, 2)):
        base = RECORDS["none"] if defense == "none" else _shifted(RECORDS["none"], 0.1 + 0.01 * (seed - 1))
        label = "laneatt-resnet18" if defense == "none" else "laneatt-resnet18+aam++"
        _write_run(sweep / str(job), [{**r, "model": label} for r in base], defense=defense, seed=seed)
    records, runs = records_from_runs([str(sweep)])
    assert {d: sorted(by_seed) for d, by_seed in records.items()} == {"none": [0, 1, 2], "aam++": [0, 1, 2]}
    assert runs["aam++"][2] == str(sweep / "5")
    cfg = OmegaConf.create({"task": {"runs": [str(sweep)], "out_dir": None, "bootstrap": 500, "confidence": 0.95},
                            "output_dir": str(tmp_path / "report"), "seed": 0})
    compare(cfg)
    scores = {r["defense"]: r for r in json.loads((tmp_path / "report" / "defense_scores.json").read_text())}
    assert scores["aam++"]["seeds"] == 3
    assert scores["aam++"]["shadow/Accuracy"] == pytest.approx(60.0)  # none's shadow 50 + 10
    assert scores["aam++"]["shadow/Accuracy/std"] == pytest.approx(1.0)
    assert scores["none"]["shadow/Accuracy/std"] == pytest.approx(0.0)
    gains = {r["category"]: r for r in json.loads((tmp_path / "report" / "defense_gain.json").read_text())}
    shadow = gains["shadow"]
    assert shadow["Accuracy/gain"] == pytest.approx(10.0)
    assert 9.0 - 1e-9 <= shadow["Accuracy/low"] < 10.0 < shadow["Accuracy/high"] <= 11.0 + 1e-9  # the seeds' spread
    assert shadow["Accuracy/distinguishable"] is True
    assert gains["original"]["Accuracy/distinguishable"] is False  # clean images unchanged: gain exactly 0
    text = (tmp_path / "report" / "compare.md").read_text()
    assert "+10.00 [+" in text and "the 3 seeds [0, 1, 2]" in text and "60.00 ± 1.00" in text


def test_report_only_from_a_multirun_directory_and_a_single_run(tmp_path):
    sweep = tmp_path / "multirun"
    _write_run(sweep / "0", RECORDS["pgd"], defense="pgd")
    _write_run(sweep / "1", RECORDS["none"], defense="none")
    _write_run(tmp_path / "elsewhere", RECORDS["aam++"])  # no config: the defense comes from the label
    records, runs = records_from_runs([str(sweep), str(tmp_path / "elsewhere")])
    assert list(records) == ["none", "pgd", "aam++"]
    assert runs["aam++"] == {0: str(tmp_path / "elsewhere")} and runs["pgd"] == {0: str(sweep / "0")}
    cfg = OmegaConf.create({"task": {"runs": [str(sweep), str(tmp_path / "elsewhere")], "out_dir": None},
                            "output_dir": str(tmp_path / "report")})
    assert compare(cfg) == pytest.approx(72.5)
    pivot = {r["defense"]: r for r in json.loads((tmp_path / "report" / "defense_gain.json").read_text())
             if r["category"] == "average"}
    assert pivot["aam++"]["Accuracy/gain"] == pytest.approx(12.5)
    assert pivot["pgd"]["Accuracy/gain"] == pytest.approx(-2.5)
    _write_run(tmp_path / "again", RECORDS["pgd"], defense="pgd")
    with pytest.raises(ValueError, match="defense 'pgd' with seed=0 found twice"):
        records_from_runs([str(sweep), str(tmp_path / "again")])


def test_a_defense_layer_missing_from_the_model_fails_before_any_run_trains(tmp_path, monkeypatch):
    import lanevil_train.tasks.compare as compare_module

    def no_training(*args, **kwargs):
        raise AssertionError("a run was started before every defense was checked")

    monkeypatch.setattr(compare_module, "run_defense", no_training)
    user = ["task=compare", "task.defenses=[none,aam]", "model.attention_layer=nolayer", *TINY]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
            cfg = compose(config_name="config", overrides=[*user, f"task.out_dir={tmp_path}"])
            with pytest.raises(ValueError, match=r"task=compare: the defense=aam run cannot use this model: "
                                                 r"model.attention_layer='nolayer' \(defense.callback.layer is "
                                                 r"\$\{model.attention_layer\}\): AttentionAreaMixing: "
                                                 r"layer='nolayer' is not a module of LaneDetector; some names: "
                                                 r".*'backbone'.*Nothing was trained"):
                compare(cfg, overrides=user)
            cfg = compose(config_name="config", overrides=[*user[:2], *TINY, f"task.out_dir={tmp_path}"])
            with pytest.raises(AssertionError, match="a run was started"):  # the shipped layer passes the check
                compare(cfg, overrides=[*user[:2], *TINY])
    finally:
        GlobalHydra.instance().clear()
    assert not (tmp_path / "runs").exists()


def test_report_only_needs_a_defense_besides_none_and_names_the_runs_without_results(tmp_path, caplog):
    sweep = tmp_path / "multirun"
    _write_run(sweep / "0", RECORDS["none"], defense="none")
    (sweep / "1" / "checkpoints").mkdir(parents=True)  # a run that failed before it was scored
    with pytest.raises(ValueError, match=rf"only 'none' has results \({sweep / '0'}\); need the results of 'none' "
                                         rf"and at least one other defense.*skipped for having no results .*"
                                         rf"\['{sweep / '1'}'\]"):
        records_from_runs([str(sweep)])
    (sweep / "1" / "robustness").mkdir()
    (sweep / "1" / "robustness" / "per_image.jsonl").write_text("")  # killed before its first record
    with pytest.raises(ValueError, match=rf"only 'none' has results.*\['{sweep / '1'}'\]"):
        records_from_runs([str(sweep)])
    with pytest.raises(ValueError, match=rf"task.runs=\['{sweep / '0'}'\]: only 'none' has results"):
        records_from_runs([str(sweep / "0")])
    _write_run(sweep / "2", RECORDS["pgd"], defense="pgd")
    with caplog.at_level("WARNING"):
        records, _ = records_from_runs([str(sweep)])
    assert list(records) == ["none", "pgd"]
    assert f"skipped for having no results (no complete robustness/per_image.jsonl): ['{sweep / '1'}']" in caplog.text


def test_seeds_change_the_training_but_not_the_suite(tmp_path):
    import torch

    out = tmp_path / "compare"
    args = ["task=compare", "task.defenses=[none,hsv]", "task.seeds=[0,1]", *TINY, "trainer.max_steps=2",
            "trainer.limit_val_batches=0", "task.cases=1", "task.illusions=[rail_shadow,vehicle]",
            "task.severities=[3]", "task.test_after_fit=false", "task.bootstrap=200"]
    run_in_process(args, out)
    runs = {(d, s): out / "runs" / d / f"seed{s}" for d in ("none", "hsv") for s in (0, 1)}
    for (defense, seed), run in runs.items():
        config = OmegaConf.load(run / "config.yaml")
        assert (config.defense.name, config.seed) == (defense, seed)
    weights = {key: torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["state_dict"]
               for key, run in runs.items()}
    name = next(k for k in weights["none", 0] if k.endswith("weight"))
    assert not torch.equal(weights["none", 0][name], weights["none", 1][name])  # another seed trains another model
    suites = {key: [(r["key"], r["gt_lanes"]) for r in read_records(run / "robustness" / "per_image.jsonl")]
              for key, run in runs.items()}
    assert len(suites["none", 0]) == 3 and all(s == suites["none", 0] for s in suites.values())  # one suite
    scores = {r["defense"]: r for r in json.loads((out / "defense_scores.json").read_text())}
    assert scores["hsv"]["seeds"] == 2 and "average/Accuracy/std" in scores["hsv"]
    gains = json.loads((out / "defense_gain.json").read_text())
    assert all(r["Accuracy/low"] <= r["Accuracy/gain"] <= r["Accuracy/high"] for r in gains)
    assert "the 2 seeds [0, 1]" in (out / "compare.md").read_text()
