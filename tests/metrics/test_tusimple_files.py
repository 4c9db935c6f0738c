"""File-level TuSimple evaluation, its CLI, and agreement with the torchmetrics Metric."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lanevil_train.lanes import TUSIMPLE_H_SAMPLES, rows_to_lane
from lanevil_train.metrics import TuSimpleMetric, evaluate_tusimple_files, tusimple_image_scores
from lanevil_train.metrics.__main__ import main

REPO = Path(__file__).resolve().parents[2]
YS = [int(y) for y in TUSIMPLE_H_SAMPLES]  # 56 rows


def _write_lines(path: Path, objs) -> Path:
    path.write_text("".join(json.dumps(o) + "\n" for o in objs))
    return path


EXPECTED = {"Accuracy": 0.75, "FP": 0.25, "FN": 0.25, "F1": 0.75,
            "F1_count": 0.75, "TP_count": 3, "FP_count": 1, "FN_count": 1}


def _two_images(tmp_path: Path) -> tuple[Path, Path]:
    """Image a: 2 GT, 2 good preds -> (1, 0, 0). Image b: 2 GT, one good + one far pred ->
    acc 0.5, fp 1/2, fn 1/2. Means: Accuracy .75, FP .25, FN .25; F1 = .75 (P = R = .75).
    Lanes: TP 2 + 1, FP 0 + 1, FN 0 + 1 -> F1_count = 6 / 8 = .75."""
    pred, gt = _two_image_objects()
    return _write_lines(tmp_path / "pred.json", pred), _write_lines(tmp_path / "gt.json", gt)


def _two_image_objects() -> tuple[list[dict], list[dict]]:
    """(prediction lines, GT lines) of `_two_images`: predictions b then a, GT a then b."""
    l1, l2 = [300] * 56, [-2] * 10 + [700] * 46
    gt = [
        {"lanes": [l1, l2], "h_samples": YS, "raw_file": "clips/a/20.jpg"},
        {"lanes": [l1, l2], "h_samples": YS, "raw_file": "clips/b/20.jpg"},
    ]
    pred = [
        {"lanes": [[305.5] * 56, [-2] * 10 + [690] * 46], "raw_file": "clips/b/20.jpg", "run_time": 10},
        {"lanes": [[310] * 56, [-2] * 10 + [712] * 46], "raw_file": "clips/a/20.jpg"},
    ]
    pred[0]["lanes"][1] = [1000] * 56
    return pred, gt


def test_file_level_hand_computed(tmp_path):
    pred, gt = _two_images(tmp_path)
    out = evaluate_tusimple_files(pred, gt)
    assert out == pytest.approx(EXPECTED)


def test_cli_main_prints_json(tmp_path, capsys):
    pred, gt = _two_images(tmp_path)
    assert main(["tusimple", "--pred", str(pred), "--gt", str(gt)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == pytest.approx(EXPECTED)


def test_cli_silent_model_f1_count_zero(tmp_path, capsys):
    """A prediction file with no lanes: the papers' F1 reads 2/3 (FP 0, FN 1), the command's F1_count 0."""
    _, gt = _two_image_objects()
    silent = [{"lanes": [], "raw_file": g["raw_file"]} for g in gt]
    pred_path, gt_path = _write_lines(tmp_path / "silent.json", silent), _write_lines(tmp_path / "gt.json", gt)
    assert main(["tusimple", "--pred", str(pred_path), "--gt", str(gt_path)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == pytest.approx({"Accuracy": 0.0, "FP": 0.0, "FN": 1.0, "F1": 2 / 3,
                                     "F1_count": 0.0, "TP_count": 0, "FP_count": 0, "FN_count": 4})


def test_cli_subprocess(tmp_path):
    pred, gt = _two_images(tmp_path)
    res = subprocess.run(
        [sys.executable, "-m", "lanevil_train.metrics", "tusimple", "--pred", str(pred), "--gt", str(gt)],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout) == pytest.approx(EXPECTED)


def test_cli_bad_input_exit_code_and_message(tmp_path, capsys):
    _, gt = _two_images(tmp_path)
    bad = tmp_path / "bad.json"
    bad.write_text('{"lanes": [], "raw_file": "clips/a/20.jpg"}\n{"lanes": [\n')
    assert main(["tusimple", "--pred", str(bad), "--gt", str(gt)]) == 1
    err = capsys.readouterr().err
    assert f"{bad}:2" in err and "malformed JSON" in err


def test_metric_equals_file_level(tmp_path):
    rng = np.random.default_rng(11)
    gt_objs, pred_objs, gts, preds = [], [], [], []
    ys = np.asarray(YS, dtype=float)
    for i in range(60):
        g_rows, p_rows = [], []
        for _ in range(int(rng.integers(1, 6))):
            xs = np.round(rng.uniform(200, 1100) + rng.uniform(-1.5, 1.5) * (ys - 400))
            start = int(rng.integers(0, 30))
            xs[:start] = -2
            xs[xs < 0] = -2
            if np.count_nonzero(xs >= 0) < 2:
                continue
            g_rows.append(xs)
            if rng.random() < 0.8:
                p_rows.append(np.where(xs >= 0, np.maximum(xs + rng.normal(0, 12, 56), 0), -2.0))
        for _ in range(int(rng.integers(0, 3))):
            p_rows.append(np.maximum(np.round(rng.uniform(0, 1280) + 0.5 * (ys - 400)), -2))
        p_rows = [p for p in p_rows if np.count_nonzero(p >= 0) >= 2 and np.all((p >= 0) | (p == -2))]
        raw = f"clips/{i}/20.jpg"
        gt_objs.append({"lanes": [r.tolist() for r in g_rows], "h_samples": YS, "raw_file": raw})
        pred_objs.append({"lanes": [r.tolist() for r in p_rows], "raw_file": raw, "run_time": 5})
        gts.append([rows_to_lane(r, ys) for r in g_rows])
        preds.append([rows_to_lane(r, ys) for r in p_rows])
    file_out = evaluate_tusimple_files(
        _write_lines(tmp_path / "p.json", pred_objs[::-1]), _write_lines(tmp_path / "g.json", gt_objs)
    )
    metric = TuSimpleMetric()
    metric.update(preds[:25], gts[:25], [ys] * 25)
    metric.update(preds[25:], gts[25:], ys)  # one array for the whole batch
    out = {k: float(v) for k, v in metric.compute().items()}
    assert set(out) == {"Accuracy", "FP", "FN", "F1", "F1_count"}
    assert out == pytest.approx({k: file_out[k] for k in out}, abs=1e-12)
    counts = (int(metric.tp_count), int(metric.fp_count), int(metric.fn_count))
    assert counts == (file_out["TP_count"], file_out["FP_count"], file_out["FN_count"]) and min(counts) > 0
    # h_samples=None uses only the rows some GT lane covers: rows where every GT lane is -2
    # drop out of the per-lane denominator, so it is NOT the official score here
    guessed = TuSimpleMetric()
    guessed.update(preds, gts)
    assert float(guessed.compute()["Accuracy"]) != pytest.approx(file_out["Accuracy"], abs=1e-6)
    assert 0.3 < file_out["Accuracy"] < 0.99 and file_out["FP"] > 0 and file_out["FN"] > 0


def test_error_malformed_json_names_file_and_line(tmp_path):
    _, gt = _two_images(tmp_path)
    bad = tmp_path / "pred_bad.json"
    bad.write_text('{"lanes": [], "raw_file": "clips/a/20.jpg"}\n\n{"lanes": [1, 2}\n')
    with pytest.raises(ValueError, match=rf"{bad}:3: malformed JSON"):
        evaluate_tusimple_files(bad, gt)


def test_error_missing_prediction_names_raw_file(tmp_path):
    pred, gt = _two_images(tmp_path)
    lines = pred.read_text().splitlines()
    pred.write_text(lines[1] + "\n")  # only clips/a
    with pytest.raises(ValueError, match=r"no prediction .* raw_file 'clips/b/20.jpg'"):
        evaluate_tusimple_files(pred, gt)


def test_error_unknown_raw_file_and_duplicates(tmp_path):
    pred, gt = _two_images(tmp_path)
    _write_lines(pred, [{"lanes": [], "raw_file": "clips/zzz/20.jpg"}])
    with pytest.raises(ValueError, match=r"pred.json:1: raw_file 'clips/zzz/20.jpg' is not in the GT"):
        evaluate_tusimple_files(pred, gt)
    _write_lines(pred, [{"lanes": [], "raw_file": "clips/a/20.jpg"}] * 2)
    with pytest.raises(ValueError, match=r"pred.json:2: duplicate prediction"):
        evaluate_tusimple_files(pred, gt)


def test_error_lane_length_and_missing_key(tmp_path):
    pred, gt = _two_images(tmp_path)
    _write_lines(pred, [
        {"lanes": [], "raw_file": "clips/a/20.jpg"},
        {"lanes": [[1, 2, 3]], "raw_file": "clips/b/20.jpg"},
    ])
    with pytest.raises(ValueError, match=r"pred.json:2: Format of lanes error: prediction lane 0 of raw_file "
                                         r"'clips/b/20.jpg' has 3 x values .* 56"):
        evaluate_tusimple_files(pred, gt)
    _write_lines(pred, [{"lanes": []}])
    with pytest.raises(ValueError, match=r"pred.json:1: missing key\(s\) \['raw_file'\]"):
        evaluate_tusimple_files(pred, gt)
    with pytest.raises(FileNotFoundError, match="nope.json"):
        evaluate_tusimple_files(tmp_path / "nope.json", gt)


def test_file_sum_runs_in_prediction_file_order(tmp_path):
    """The official loop sums per-image scores in the prediction file's order; float sums depend on it."""
    ks = next(ks for ks in ((a, b, c) for a in range(1, 56) for b in range(1, 56) for c in range(1, 56))
              if (ks[0] / 56 + ks[1] / 56) + ks[2] / 56 != (ks[2] / 56 + ks[1] / 56) + ks[0] / 56)
    gt, pred = [], []
    for i, k in enumerate(ks):  # one GT lane at x=500; the prediction agrees on its first k rows only
        raw = f"clips/{i}/20.jpg"
        gt.append({"lanes": [[500] * 56], "h_samples": YS, "raw_file": raw})
        pred.append({"lanes": [[500] * k + [900] * (56 - k)], "raw_file": raw, "run_time": 1})
    gt_path = _write_lines(tmp_path / "g.json", gt)
    forward = evaluate_tusimple_files(_write_lines(tmp_path / "p.json", pred), gt_path)
    backward = evaluate_tusimple_files(_write_lines(tmp_path / "r.json", pred[::-1]), gt_path)
    assert forward["Accuracy"] == ((ks[0] / 56 + ks[1] / 56) + ks[2] / 56) / 3
    assert backward["Accuracy"] == ((ks[2] / 56 + ks[1] / 56) + ks[0] / 56) / 3
    assert forward["Accuracy"] != backward["Accuracy"]


NON_FINITE = [(float("nan"), "nan"), (float("inf"), "inf"), (float("-inf"), "-inf")]  # JSON NaN, Infinity, -Infinity


@pytest.mark.parametrize("value, shown", NON_FINITE)
def test_error_non_finite_prediction_x_names_file_line_raw_file_and_lane(tmp_path, value, shown):
    pred, gt = _two_image_objects()
    pred[0]["lanes"][1][5] = value  # clips/b, line 1 of the prediction file, lane 1, row y = 210
    pred_path, gt_path = _write_lines(tmp_path / "pred.json", pred), _write_lines(tmp_path / "gt.json", gt)
    assert "NaN" in pred_path.read_text() or "Infinity" in pred_path.read_text()
    with pytest.raises(ValueError) as err:
        evaluate_tusimple_files(pred_path, gt_path)
    assert str(err.value) == (
        f"{pred_path}:1: prediction lane 1 of raw_file 'clips/b/20.jpg' has a non-finite x ({shown}) at h_sample "
        f"index 5 (y = 210); expected a finite x in pixels, or -2 for 'no point'")


@pytest.mark.parametrize("value, shown", NON_FINITE)
def test_error_non_finite_gt_x_names_the_ground_truth_side(tmp_path, value, shown):
    pred, gt = _two_image_objects()
    gt[1]["lanes"][0][0] = value  # clips/b, line 2 of the GT file, lane 0, row y = 160
    pred_path, gt_path = _write_lines(tmp_path / "pred.json", pred), _write_lines(tmp_path / "gt.json", gt)
    with pytest.raises(ValueError) as err:
        evaluate_tusimple_files(pred_path, gt_path)
    assert str(err.value) == (
        f"{gt_path}:2: ground truth lane 0 of raw_file 'clips/b/20.jpg' has a non-finite x ({shown}) at h_sample "
        f"index 0 (y = 160); expected a finite x in pixels, or -2 for 'no point'")


@pytest.mark.parametrize("value, shown", NON_FINITE)
def test_error_non_finite_gt_h_samples(tmp_path, value, shown):
    pred, gt = _two_image_objects()
    gt[0]["h_samples"] = YS[:3] + [value] + YS[4:]  # clips/a, line 1 of the GT file
    pred_path, gt_path = _write_lines(tmp_path / "pred.json", pred), _write_lines(tmp_path / "gt.json", gt)
    with pytest.raises(ValueError) as err:
        evaluate_tusimple_files(pred_path, gt_path)
    assert str(err.value) == (
        f"{gt_path}:1: ground truth h_samples of raw_file 'clips/a/20.jpg' has a non-finite y ({shown}) at index 3; "
        f"expected finite image rows in pixels")
    gt[0]["h_samples"] = "rows"
    _write_lines(gt_path, gt)
    with pytest.raises(ValueError, match=rf"{gt_path}:1: ground truth h_samples of raw_file 'clips/a/20.jpg' must be "
                                         r"a list of numbers"):
        evaluate_tusimple_files(pred_path, gt_path)


def test_non_finite_error_through_the_command_line(tmp_path, capsys):
    pred, gt = _two_image_objects()
    pred[1]["lanes"][0][55] = float("nan")  # clips/a, line 2 of the prediction file
    pred_path, gt_path = _write_lines(tmp_path / "pred.json", pred), _write_lines(tmp_path / "gt.json", gt)
    assert main(["tusimple", "--pred", str(pred_path), "--gt", str(gt_path)]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == (
        f"error: {pred_path}:2: prediction lane 0 of raw_file 'clips/a/20.jpg' has a non-finite x (nan) at h_sample "
        f"index 55 (y = 710); expected a finite x in pixels, or -2 for 'no point'\n")


def test_image_scores_name_the_non_finite_argument():
    ys = np.asarray(YS, dtype=float)
    good = np.full((2, 56), 300.0)
    bad = good.copy()
    bad[1, 7] = np.nan
    with pytest.raises(ValueError) as err:
        tusimple_image_scores(bad, good, ys)
    assert str(err.value) == ("pred_rows: lane 1 has a non-finite x (nan) at h_sample index 7; expected a finite x "
                              "in pixels, or -2 (any x < 0) for 'no point'")
    bad[1, 7] = -np.inf
    with pytest.raises(ValueError, match=r"^gt_rows: lane 1 has a non-finite x \(-inf\) at h_sample index 7"):
        tusimple_image_scores(good, bad, ys)
    ys_bad = ys.copy()
    ys_bad[2] = np.inf
    with pytest.raises(ValueError, match=r"^h_samples: non-finite y \(inf\) at index 2"):
        tusimple_image_scores(good, good, ys_bad)
    assert tusimple_image_scores(good, good, ys) == (1.0, 0.0, 0.0)  # valid input still scores


@pytest.mark.parametrize("value", ["300", True, None])
def test_error_a_non_number_x_is_not_turned_into_a_number(tmp_path, value):
    pred, gt = _two_image_objects()
    pred[0]["lanes"][1][5] = value  # numpy would read "300" as 300.0 and true as 1.0
    pred_path, gt_path = _write_lines(tmp_path / "pred.json", pred), _write_lines(tmp_path / "gt.json", gt)
    with pytest.raises(ValueError, match=rf"^{pred_path}:1: prediction lane 1 of raw_file 'clips/b/20.jpg' must be a "
                                         r"list of numbers, got \["):
        evaluate_tusimple_files(pred_path, gt_path)


def test_error_raw_file_that_is_not_a_string(tmp_path):
    pred, gt = _two_image_objects()
    pred[1]["raw_file"] = ["clips/a/20.jpg"]
    pred_path, gt_path = _write_lines(tmp_path / "pred.json", pred), _write_lines(tmp_path / "gt.json", gt)
    with pytest.raises(ValueError, match=rf"^{pred_path}:2: raw_file must be a non-empty string \(the image's path\), "
                                         r"got \['clips/a/20.jpg'\]"):
        evaluate_tusimple_files(pred_path, gt_path)


@pytest.mark.parametrize("flag, value, message", [
    ("--pixel-thresh", "-5", "pixel_thresh (--pixel-thresh) must be a finite number of pixels > 0 (official: 20), "
                             "got -5.0"),
    ("--pixel-thresh", "0", "got 0.0"),
    ("--pixel-thresh", "nan", "pixel_thresh (--pixel-thresh) must be a finite number of pixels > 0"),
    ("--pixel-thresh", "inf", "got inf"),
    ("--pt-thresh", "2", "pt_thresh (--pt-thresh) must be a fraction of matched points in (0, 1] (official: 0.85), "
                         "got 2.0"),
    ("--pt-thresh", "0", "got 0.0"),
    ("--pt-thresh", "nan", "pt_thresh (--pt-thresh) must be"),
])
def test_cli_bad_thresholds_are_refused(tmp_path, capsys, flag, value, message):
    pred, gt = _two_images(tmp_path)
    assert main(["tusimple", "--pred", str(pred), "--gt", str(gt), flag, value]) == 1
    captured = capsys.readouterr()
    assert captured.out == "" and message in captured.err


def test_threshold_edges_still_score(tmp_path):
    pred, gt = _two_images(tmp_path)
    assert evaluate_tusimple_files(pred, gt, pixel_thresh=20, pt_thresh=1.0)["Accuracy"] > 0
    with pytest.raises(ValueError, match="pixel_thresh"):
        evaluate_tusimple_files(pred, gt, pixel_thresh="20")
