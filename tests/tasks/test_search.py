"""task=search: a study over one illusion's parameters writes consistent results, resumes with only the missing
trials, refuses other settings, and bad settings fail before any driving."""

from __future__ import annotations

import csv
import json
from dataclasses import replace

import numpy as np
import pytest

from lanevil_train.closed_loop.collisions import obstacles
from lanevil_train.closed_loop.episode import Run, case_scene, render_view
from lanevil_train.illusions import ILLUSIONS
from lanevil_train.lanes import default_h_samples
from lanevil_train.metrics import tusimple_lane_scores, tusimple_summary
from lanevil_train.sim.vehicle import VehicleState
from lanevil_train.tasks.config_check import ConfigError, check_config
from lanevil_train.tasks.search import OpenLoopScore, window_peak
from tests.tasks.cli_helpers import composed, run_in_process

# a short closed loop on tiny images: 5 control steps a second, a 1 s window, one scene and one test case
SMALL = ["task=search", "task.policy=truth", "task.illusion=rail_shadow", "task.size=[72,128]", "task.control_hz=5",
         "task.window_s=1.0", "task.after_s=0", "task.start_before_m=[2,3]", "task.scenes=1", "task.cases=1",
         "progress=none"]


def _read(out):
    trials = list(csv.DictReader((out / "trials.csv").open()))
    return (trials, json.loads((out / "best_parameters.json").read_text()),
            json.loads((out / "rescore.json").read_text()),
            [json.loads(line) for line in (out / "study.jsonl").read_text().splitlines()])


def _check_consistent(out, count):
    trials, best, rescore, study = _read(out)
    values = [float(row["value"]) for row in trials]
    assert [int(row["trial"]) for row in trials] == list(range(count)) and best["trials"] == count
    assert best["value"] == max(values) and float(trials[-1]["best_so_far"]) == max(values)
    top = trials[best["best_trial"]]
    space = ILLUSIONS["rail_shadow"].parameters()
    assert best["point"] == space.check({p.name: float(top[p.name]) for p in space.searched})
    assert best["point"]["post_spacing_m"] == 2.5  # the fixed parameter, filled in
    for key in ("severity_3", "severity_5", "clean"):
        assert best[key] >= 0.0 and rescore[key] >= 0.0
    assert rescore["point"] == best["point"] and rescore["cases"] == {"first_seed": 1000000, "count": 1, "repeats": 1}
    assert best["scenes"] == {"first_seed": 3000000, "count": 1, "repeats": 1}
    for name in ("search.png", "worst_illusion.png"):
        assert (out / name).stat().st_size > 1000, name
    return study


def test_a_search_writes_its_results_and_a_rerun_runs_only_the_missing_trials(tmp_path, monkeypatch):
    out = tmp_path / "search"
    args = [*SMALL, f"task.out_dir={out}"]
    value = run_in_process([*args, "task.trials=2"], tmp_path / "run")
    first = _check_consistent(out, 2)
    assert value == json.loads((out / "best_parameters.json").read_text())["value"]
    import lanevil_train.tasks.search as task

    suggested = []
    real_suggest = task.suggest
    monkeypatch.setattr(task, "suggest", lambda trial, illusion: suggested.append(trial.number) or
                        real_suggest(trial, illusion))
    run_in_process([*args, "task.trials=3"], tmp_path / "run")
    assert suggested == [2]  # one new trial; the comparisons were kept
    again = _check_consistent(out, 3)
    trials = [record for record in again if record["key"].startswith("trial/")]
    assert again[:len(first)] == first and len(trials) == 3  # the first two trials and the comparisons unchanged
    assert trials[2]["params"] != trials[0]["params"] and trials[2]["params"] != trials[1]["params"]
    with pytest.raises(ValueError, match="holds results of another evaluation"):
        run_in_process([*args, "task.trials=3", "task.window_s=2.0"], tmp_path / "run")


@pytest.mark.parametrize("override, message", [
    ("task.illusion=puddle", "task.illusion: expected one of road_crack, "),
    ("task.trials=0", "task.trials: expected an integer >= 1, got 0"),
    ("task.objective=f1", "task.objective: expected one of closed_loop, open_loop, got 'f1'"),
    ("task.scenes=0", "task.scenes: expected an integer >= 1"),
    ("task.start=best", "task.start: expected one of severities, random, got 'best'"),
])
def test_bad_settings_are_refused_naming_the_key(override, message):
    with pytest.raises(ConfigError, match=message):
        check_config(composed([*SMALL, override]))


def test_a_detector_search_needs_a_checkpoint():
    with pytest.raises(ConfigError, match="ckpt_path: task=search drives a trained detector"):
        check_config(composed(["task=search"]))


@pytest.mark.parametrize("override, message", [
    ("task.search_seed=1000000", r"task.search_seed: the search scenes \[1000000, 1000001\) overlap the test cases"),
    ("task.objective=open_loop", "task.objective: open_loop scores a lane detector's lanes; task.policy=truth"),
])
def test_settings_that_cannot_work_together_fail_before_any_driving(tmp_path, override, message):
    with pytest.raises(ValueError, match=message):
        run_in_process([*SMALL, override, f"task.out_dir={tmp_path}"], tmp_path / "run")
    assert not (tmp_path / "study.jsonl").exists()


def test_the_closed_loop_objective_is_the_peak_deviation_in_the_attack_window():
    trace = [{"t": 0.1 * i, "s": 2.0 * i, "deviation": d} for i, d in enumerate([0.9, 0.1, -0.3, 0.2, -0.5, 0.05])]
    assert window_peak(trace, region_start_m=2.0, window_s=0.25) == 0.3  # steps at 0.1-0.3 s after the entry
    assert window_peak(trace, region_start_m=5.0, window_s=0.2) == 0.5  # entered at 0.25 s: steps at 0.3 and 0.4 s
    assert window_peak(trace, region_start_m=50.0, window_s=1.0) == 0.9  # never entered: the whole run


def test_a_run_at_a_severitys_point_sees_what_that_severitys_run_sees():
    run = Run("case000", 1000000, "rail_shadow", 4, 0, 0.0, (5.0, 20.0))
    state, size = VehicleState(s=3.0, d=0.3, heading=0.01), (72, 128)
    at_severity = render_view(run, state, size)[0]
    point = tuple(ILLUSIONS["rail_shadow"].point(4).items())
    assert np.array_equal(render_view(replace(run, severity=0, point=point), state, size)[0], at_severity)
    assert not np.array_equal(render_view(replace(run, severity=0), state, size)[0], at_severity)


class _SeesOnlyClean:
    """A stand-in detector: the true lanes of a clean scene's image, none once an illusion changed it."""

    def __init__(self, seed, size):
        self.scene, self.clean = case_scene(seed, size)

    def lanes(self, image):
        return self.scene.lanes()[0] if np.array_equal(image, self.clean) else []


def test_the_open_loop_objective_is_the_f1_drop_from_clean():
    seed, size, fence = 3000000, (72, 128), ILLUSIONS["fence_shadow"]
    score = OpenLoopScore(_SeesOnlyClean(seed, size), fence, [seed], size)
    assert score.clean_f1 == 100.0 and score(0) == 0.0
    # the illusion hides every lane from this detector: the drop is 100 minus the F1 of predicting none
    none = tusimple_lane_scores([], score.samples[0][2], default_h_samples(72), pixel_thresh=20.0 * 128 / 1280)
    assert score(5) == pytest.approx(100.0 - 100.0 * tusimple_summary(*none, 1)["F1"]) and score(5) > 30.0
    assert score(fence.point(5)) == score(5)


@pytest.mark.parametrize("name", ["vehicle", "guard_rail"])
def test_the_radar_sees_a_points_objects_as_a_severitys(name):
    scene = case_scene(1000000, (72, 128))[0]
    for severity in (1, 5):
        at_severity = [o.as_dict() for o in obstacles(scene, name, severity, 7)]
        assert at_severity and [o.as_dict() for o in obstacles(scene, name, ILLUSIONS[name].point(severity), 7)] \
            == at_severity
    fewer = {**ILLUSIONS[name].point(5), ("count" if name == "vehicle" else "sides"): 1}
    assert len(obstacles(scene, name, fewer, 7)) == 1


def test_a_study_starts_at_the_severity_points_and_a_resumed_one_does_not_try_them_again(tmp_path):
    """task.start=severities (the default): the first trials are severities 5, 4, 3... so the best is never below
    severity 5's on the search scenes; a rerun with more trials goes on from there; random: TPE's own start."""
    out = tmp_path / "search"
    args = [*SMALL, f"task.out_dir={out}"]
    space = ILLUSIONS["rail_shadow"].parameters()

    def searched(severity):
        return {p.name: ILLUSIONS["rail_shadow"].point(severity)[p.name] for p in space.searched}

    run_in_process([*args, "task.trials=2"], tmp_path / "run")
    trials, best, _, study = _read(out)
    params = [r["params"] for r in study if r["key"].startswith("trial/")]
    assert params == [searched(5), searched(4)]
    assert best["value"] >= best["severity_5"] and float(trials[0]["value"]) == best["severity_5"]
    run_in_process([*args, "task.trials=4"], tmp_path / "run")
    params = [r["params"] for r in _read(out)[3] if r["key"].startswith("trial/")]
    assert params == [searched(5), searched(4), searched(3), searched(2)]
    random_out = tmp_path / "random"
    run_in_process([*SMALL, f"task.out_dir={random_out}", "task.trials=1", "task.start=random"], tmp_path / "run")
    first = [r["params"] for r in _read(random_out)[3] if r["key"].startswith("trial/")][0]
    assert first not in [searched(s) for s in range(1, 6)]
