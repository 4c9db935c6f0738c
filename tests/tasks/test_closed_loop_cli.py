"""task=closed_loop end to end: a detector checkpoint drives the runs, the report and animation are written from
runs.jsonl and the traces, an interrupted run resumes, bad settings fail before any driving."""

from __future__ import annotations

import json

import pytest
import torch

from lanevil_train.closed_loop.run_scores import run_scores
from lanevil_train.results_log import ResultsLog
from lanevil_train.tasks import run_task
from lanevil_train.tasks.builders import build_model, model_config
from lanevil_train.tasks.config_check import ConfigError, check_config
from tests.tasks.cli_helpers import TINY, composed, run_in_process

SMALL = ["task.cases=1", "task.repeats=1", "task.size=[90,160]", "progress=none"]


def _tiny_checkpoint(path):
    """An untrained LaneATT at the TINY input size, saved as task=train saves it (weights + build config)."""
    torch.manual_seed(0)
    model = build_model(model_config(composed(TINY)))
    torch.save({"state_dict": model.state_dict(), "lanevil_model": model.build_config}, path)
    return path


def test_a_detector_checkpoint_drives_clean_and_perturbed_runs_and_the_report_is_written(tmp_path):
    ckpt = _tiny_checkpoint(tmp_path / "tiny.ckpt")
    out = tmp_path / "loop"
    run_in_process(["task=closed_loop", f"ckpt_path={ckpt}", *SMALL, "task.illusions=[rail_shadow]",
                    "task.severities=[2,5]", f"task.out_dir={out}"], tmp_path / "run")
    records = ResultsLog(out / "runs.jsonl").records()
    assert [(r["model"], r["illusion"], r["severity"]) for r in records] == \
        [("laneatt-resnet18", "rail_shadow", s) for s in (0, 2, 5)]
    assert len({r["start_m"] for r in records}) == 1  # the clean twin starts where the perturbed runs start
    for record in records:
        trace = [json.loads(line) for line in (out / record["trace"]).read_text().splitlines()]
        assert len(trace) == record["steps"] and trace[0]["s"] == pytest.approx(record["start_m"])
        assert trace[0]["lanes"] >= 0 and "estimate" in trace[0]
        rescored = run_scores(trace, record["region_m"][0], record["lane_width_m"])
        assert {k: record[k] for k in rescored} == rescored
    table = json.loads((out / "asr_by_category.json").read_text())
    row = next(r for r in table if r["category"] == "shadow")
    assert row["runs"] == 2 and row["ASR (%)"] == pytest.approx(50.0 * sum(r["success"] for r in records[1:]))
    assert row["clean ASR (%)"] == pytest.approx(100.0 * records[0]["success"])
    for name in ("closed_loop.md", "asr.png", "deviation.png", "worst_run.gif", "asr_by_illusion.csv", "report.html"):
        assert (out / name).is_file(), name
    from PIL import Image

    with Image.open(out / "worst_run.gif") as gif:
        assert gif.n_frames == max(r["steps"] for r in records) and gif.size[0] == 640  # two 320-px views


def test_an_interrupted_closed_loop_resumes_driving_only_the_unfinished_runs(tmp_path, monkeypatch):
    out = tmp_path / "loop"
    args = ["task=closed_loop", "task.policy=truth", *SMALL, "task.illusions=[tire_marks,vehicle]",
            f"task.out_dir={out}", "task.animate=false"]
    run_in_process(args, tmp_path / "run")
    log = out / "runs.jsonl"
    first = ResultsLog(log).records()
    assert len(first) == 4 and not any(r["success"] for r in first)  # the true lanes: no attack succeeds
    kept_trace = out / first[0]["trace"]
    kept_mtime = kept_trace.stat().st_mtime_ns
    # killed while appending the third run's line: two whole lines and a torn one are left
    lines = log.read_text().splitlines(keepends=True)
    log.write_text("".join(lines[:2]) + lines[2][:25])
    import lanevil_train.tasks.closed_loop as task

    driven = []
    real_drive = task.drive
    monkeypatch.setattr(task, "drive", lambda run, policy, settings: driven.append(run.key) or
                        real_drive(run, policy, settings))
    run_in_process(args, tmp_path / "run")
    assert driven == [first[2]["run"], first[3]["run"]]
    again = ResultsLog(log).records()
    assert again == first
    assert kept_trace.stat().st_mtime_ns == kept_mtime


@pytest.mark.parametrize("override, message", [
    ([], "ckpt_path: task=closed_loop drives a trained detector"),
    (["task.policy=truth", "task.start_before_m=[10,5]"], "task.start_before_m"),
    (["task.policy=truth", "task.illusions=[fog]"], "task.illusions"),
    (["task.policy=truth", "task.vehicle.speed_mph=0"], "task.vehicle.speed_mph"),
    (["task.policy=truth", "task.vehicle.max_decel_mps2=0"], "task.vehicle.max_decel_mps2"),
    (["task.policy=truth", "task.longitudinal=idm"], "task.longitudinal: expected one of acc, none"),
    (["task.policy=truth", "task.acc.ttc_s=0"], "task.acc.ttc_s"),
    (["task.policy=truth", "+task.acc.ttc=1"], "task.acc.ttc: not a setting of task.acc"),
    (["task.policy=truth", "task.acc.decel_mps2=9"], "task.acc.decel_mps2: expected at most task.vehicle.max_decel"),
    (["task.models={none: /no/such.ckpt}"], "task.models"),
    (["task.policy=vlm"], "task.policy: vlm needs a VLM"),
    (["task.policy=truth", "task.controller=lqr"], "task.controller: expected one of pure_pursuit, stanley, mpc"),
    (["task.policy=truth", "task.tracker=particle"], "task.tracker: expected one of kalman, none"),
    (["task.policy=truth", "task.kalman.gate_probability=1.5"], "task.kalman.gate_probability"),
    (["task.policy=truth", "task.mpc.horizon_s=0"], "task.mpc.horizon_s"),
    (["task.policy=truth", "task.control_hz=0"], "task.control_hz"),
])
def test_bad_closed_loop_settings_fail_naming_the_key(override, message):
    cfg = composed(["task=closed_loop", *override])
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        check_config(cfg)
    with pytest.raises(ConfigError):
        run_task(cfg)


def test_a_local_vlm_with_a_textual_defense_drives_the_loop_from_its_answers(tmp_path):
    from lanevil_dev.tiny_vlm import build_tiny_vlm

    model = build_tiny_vlm("qwen2_vl", tmp_path / "tiny-qwen2-vl")
    out = tmp_path / "loop"
    run_in_process(["task=closed_loop", "model=vlm/hf", f"model.path={model}", "model.max_new_tokens=6",
                    "model.device=cpu", "defense=self_reminder", *SMALL, "task.illusions=[tire_marks]",
                    "task.vlm.frames=2", "task.animate=false", f"task.out_dir={out}"], tmp_path / "run")
    records = ResultsLog(out / "runs.jsonl").records()
    assert [(r["severity"], r["perturbed"]) for r in records] == [(0, False), (3, True)]
    assert all(r["model"].endswith("+self_reminder") for r in records)  # the defended model drove
    for record in records:
        trace = [json.loads(line) for line in (out / record["trace"]).read_text().splitlines()]
        for step in trace:
            # what the VLM said each step, how it was read, and the steering that followed
            from lanevil_train.closed_loop import parse_direction

            assert step["direction"] == parse_direction(step["answer"])
            expected = {"left": -0.5, "right": 0.5}.get(step["direction"], 0.0)
            assert step["command_deg"] == pytest.approx(expected)
    assert (out / "closed_loop.md").is_file()


def test_starts_are_random_per_repeat_fixed_by_the_seed_and_shared_by_a_runs_twin():
    from lanevil_train.tasks.closed_loop import ClosedLoopSettings

    def starts(seed):
        cfg = composed(["task=closed_loop", "task.policy=truth", "task.cases=2", "task.repeats=3",
                         "task.illusions=[tire_marks]", "task.severities=[1,4]", "task.size=[90,160]", f"seed={seed}"])
        settings = ClosedLoopSettings.from_config(cfg.task)
        runs = settings.protocol.runs(cfg.seed, settings.loop.size)
        assert len(runs) == 2 * 3 * 3
        by_repeat = {}
        for run in runs:
            by_repeat.setdefault((run.case_id, run.repeat), set()).add(run.start_m)
            assert 5.0 <= run.region[0] - run.start_m <= 10.0
        assert all(len(v) == 1 for v in by_repeat.values())  # clean twin and severities: one start
        return [next(iter(v)) for v in by_repeat.values()]

    assert starts(0) == starts(0)
    assert starts(0) != starts(1)
    assert len(set(starts(0))) == 6


def test_a_model_added_later_drives_only_its_own_runs_beside_the_finished_ones(tmp_path, monkeypatch):
    out = tmp_path / "loop"
    args = ["task=closed_loop", "task.policy=truth", *SMALL, "task.illusions=[tire_marks]", f"task.out_dir={out}",
            "task.animate=false"]
    run_in_process([*args, "task.label=first"], tmp_path / "run")
    first = ResultsLog(out / "runs.jsonl").records()
    import lanevil_train.tasks.closed_loop as task

    driven = []
    real_drive = task.drive
    monkeypatch.setattr(task, "drive", lambda run, policy, settings: driven.append(policy.name) or
                        real_drive(run, policy, settings))
    run_in_process([*args, "task.label=second"], tmp_path / "run")
    assert driven == ["second", "second"]
    records = ResultsLog(out / "runs.jsonl").records()
    assert records[:2] == first and [r["model"] for r in records] == ["first", "first", "second", "second"]
    assert json.loads((out / "traces" / "second" / "model.json").read_text()) == {"policy": "truth"}
    compared = json.loads((out / "asr_compare.json").read_text())  # one table, a column pair per model
    assert [row["category"] for row in compared] == ["road_damage", "all"]
    assert compared[0]["first ASR (%)"] == compared[0]["second ASR (%)"] == "0.0 [0.0, 79.3]"
    with pytest.raises(ValueError, match="holds results of another evaluation"):  # other settings: refused
        run_in_process([*args, "task.label=third", "task.window_s=2.0"], tmp_path / "run")
    with pytest.raises(ValueError, match="holds results of another evaluation"):  # the constant-speed car: refused
        run_in_process([*args, "task.label=third", "task.longitudinal=none"], tmp_path / "run")


def test_two_workers_drive_the_same_runs_as_one(tmp_path):
    args = ["task=closed_loop", "task.policy=truth", *SMALL, "task.illusions=[tire_marks,vehicle]",
            "task.animate=false", "task.severities=[3,5]"]
    run_in_process([*args, f"task.out_dir={tmp_path / 'one'}"], tmp_path / "run1")
    run_in_process([*args, f"task.out_dir={tmp_path / 'two'}", "task.workers=2"], tmp_path / "run2")
    one, two = ((tmp_path / name / "runs.jsonl").read_text() for name in ("one", "two"))
    assert one == two and len(one.splitlines()) == 6
    records = ResultsLog(tmp_path / "two" / "runs.jsonl").records()
    perturbed = [r for r in records if r["severity"]]
    # each perturbed run is also scored from its clean twin's path, and a standing illusion for collisions
    assert all("twin_success" in r and r["twin_max_deviation_m"] >= 0 for r in perturbed)
    assert all(isinstance(r["collision"], bool) for r in records)
    for name in ("one", "two"):
        traces = sorted((tmp_path / name / "traces").rglob("*.jsonl"))
        assert [t.read_text() for t in traces] == [
            t.read_text() for t in sorted((tmp_path / "one" / "traces").rglob("*.jsonl"))]
