"""CULane file-level evaluation and the `culane` CLI on small .lines.txt trees."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lanevil_train.metrics import CULaneMetric, culane_image_counts, evaluate_culane_dirs
from lanevil_train.metrics.__main__ import main
from lanevil_train.metrics.culane_files import OddCountWarning, read_lines_file

GT_A = [[(100.0, 589.0), (200.0, 450.0), (260.0, 300.0)], [(900.0, 589.0), (850.0, 450.0), (800.0, 300.0)]]
PRED_A = [[(104.0, 589.0), (204.0, 450.0), (264.0, 300.0)], [(1400.0, 589.0), (1300.0, 300.0)]]
GT_B = [[(600.0, 580.0), (700.0, 300.0)]]
PRED_B: list = []  # no prediction file written at all for image b -> all FN


def _write(path: Path, lanes: list) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{x:.3f} {y:.3f}" for x, y in lane) + " \n" for lane in lanes))


@pytest.fixture()
def tree(tmp_path: Path) -> tuple[Path, Path, Path]:
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _write(gt / "driver_1/05/a.lines.txt", GT_A)
    _write(pred / "driver_1/05/a.lines.txt", PRED_A)
    _write(gt / "driver_1/05/b.lines.txt", GT_B)
    lst = tmp_path / "test.txt"
    lst.write_text("/driver_1/05/a.jpg\n/driver_1/05/b.jpg\n")
    return pred, gt, lst


def test_dirs_hand_counts(tree: tuple[Path, Path, Path]) -> None:
    pred, gt, lst = tree
    res = evaluate_culane_dirs(str(pred), str(gt), str(lst))
    # a: lane 1 matched (4 px shift), the far-right pred is an FP, gt lane 2 an FN; b: 1 FN
    assert (res["TP"], res["FP"], res["FN"]) == (1, 1, 2)
    assert res["Precision"] == 0.5 and res["Recall"] == pytest.approx(1 / 3) and res["F1"] == pytest.approx(0.4)


def test_metric_equals_file_level(tree: tuple[Path, Path, Path]) -> None:
    pred, gt, lst = tree
    m = CULaneMetric()
    m.update([[np.array(lane) for lane in PRED_A], PRED_B],
             [[np.array(lane) for lane in GT_A], [np.array(lane) for lane in GT_B]])
    assert m.compute() == evaluate_culane_dirs(str(pred), str(gt), str(lst))


def test_cli_prints_json(tree: tuple[Path, Path, Path], capsys: pytest.CaptureFixture) -> None:
    pred, gt, lst = tree
    assert main(["culane", "--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(lst)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"TP", "FP", "FN", "Precision", "Recall", "F1", "images", "F1@50", "F1@75", "mF1"}
    assert (out["TP"], out["FP"], out["FN"]) == (1, 1, 2)
    # 1000 px wide lanes overlap heavily: the far-right pred now matches gt lane 2 at IoU > 0.1
    assert main(["culane", "--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(lst),
                 "--lane-width", "1000", "--iou", "0.1"]) == 0
    assert json.loads(capsys.readouterr().out)["TP"] == 2


def test_cli_subprocess_and_errors(tree: tuple[Path, Path, Path], tmp_path: Path) -> None:
    pred, gt, lst = tree
    r = subprocess.run([sys.executable, "-m", "lanevil_train.metrics", "culane", "--pred-dir", str(pred),
                        "--gt-dir", str(gt), "--list", str(lst)], capture_output=True, text=True, check=True)
    assert json.loads(r.stdout)["FN"] == 2
    assert main(["culane", "--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(tmp_path / "no.txt")]) == 1
    bad = tmp_path / "bad.lines.txt"
    bad.write_text("1 2 3 4\n5 x 6 7\n")
    with pytest.raises(ValueError, match="bad.lines.txt:2"):
        read_lines_file(str(bad))


def test_reader_matches_official_stream_semantics(tmp_path: Path) -> None:
    f = tmp_path / "x.lines.txt"
    f.write_text("1 2 3 4 5\n\n10.5 20.25 30 40 \n")
    with pytest.warns(OddCountWarning, match=rf"^{f}:1: lane 0 holds 5 numbers, an odd count; its last \(5\) is "
                                             r"dropped"):
        lanes = read_lines_file(str(f))
    assert [lane.shape for lane in lanes] == [(2, 2), (0, 2), (2, 2)]  # odd tail dropped, blank line is a lane
    assert lanes[2][0].tolist() == [10.5, 20.25]
    assert read_lines_file(str(tmp_path / "missing.lines.txt")) == []
    assert culane_image_counts(lanes, lanes) == (2, 1, 1)  # the 0-point lane is an FP and an FN


@pytest.mark.parametrize("token", ["nan", "inf", "-inf", "NaN", "Infinity", "1e999"])
def test_non_finite_prediction_names_file_line_lane_and_side(tree: tuple[Path, Path, Path], token: str) -> None:
    pred, gt, lst = tree
    bad = pred / "driver_1/05/a.lines.txt"
    bad.write_text(f"104 589 204 450 264 300\n1400 589 {token} 300\n")
    with pytest.raises(ValueError) as err:
        evaluate_culane_dirs(str(pred), str(gt), str(lst))
    assert str(err.value) == (f"{bad}:2: prediction lane 1 has a non-finite coordinate {token!r}; "
                              f"expected finite pixel numbers 'x y x y ...'")


@pytest.mark.parametrize("token", ["nan", "inf"])
def test_non_finite_ground_truth_names_the_ground_truth_side(tree: tuple[Path, Path, Path], token: str) -> None:
    pred, gt, lst = tree
    bad = gt / "driver_1/05/b.lines.txt"  # image b has no prediction file: the GT is still read
    bad.write_text(f"600 {token} 700 300\n")
    with pytest.raises(ValueError) as err:
        evaluate_culane_dirs(str(pred), str(gt), str(lst))
    assert str(err.value) == (f"{bad}:1: ground truth lane 0 has a non-finite coordinate {token!r}; "
                              f"expected finite pixel numbers 'x y x y ...'")


def test_reader_rejects_non_finite_even_in_the_ignored_odd_tail(tmp_path: Path) -> None:
    f = tmp_path / "x.lines.txt"
    f.write_text("1 2 3 4 nan\n")
    with pytest.raises(ValueError, match=rf"^{f}:1: lane 0 has a non-finite coordinate 'nan'"):
        read_lines_file(str(f))
    f.write_text("1 2 3 4 5\n")  # a finite odd tail is still ignored, as by the official reader, and said
    with pytest.warns(OddCountWarning):
        assert read_lines_file(str(f))[0].tolist() == [[1.0, 2.0], [3.0, 4.0]]


@pytest.mark.parametrize("workers", [1, 2])
def test_an_odd_count_of_numbers_scores_as_officially_and_names_file_and_line(tree, capsys, workers) -> None:
    """The official arithmetic (the last number dropped) with a warning naming each file and line, from the
    worker processes too; the score is that of the line without its last number."""
    pred, gt, lst = tree
    bad = pred / "driver_1/05/a.lines.txt"
    even = evaluate_culane_dirs(str(pred), str(gt), str(lst), workers=workers)
    lines = bad.read_text().splitlines()
    bad.write_text(f"{lines[0]} 777\n{lines[1]}\n")
    with pytest.warns(OddCountWarning) as caught:
        assert evaluate_culane_dirs(str(pred), str(gt), str(lst), workers=workers) == even
    message = str(caught[0].message)
    assert message.startswith("1 line of the .lines.txt files holds an odd count of numbers, each scored as the "
                              "official tool scores it (its last number dropped): "), message
    assert f"{bad}:1: prediction lane 0 holds 7 numbers, an odd count; its last (777) is dropped" in message
    assert main(["culane", "--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(lst)]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == even and err.startswith("warning: 1 line of the .lines.txt files") and f"{bad}:1" in err


def _culane_error(args: list[str], capsys: pytest.CaptureFixture) -> str:
    assert main(["culane", *args]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    return captured.err


def test_bad_directories_are_refused_not_scored_as_zeros(tree, tmp_path, capsys) -> None:
    pred, gt, lst = tree
    err = _culane_error(["--pred-dir", "/nonexistent", "--gt-dir", str(gt), "--list", str(lst)], capsys)
    assert err == "error: pred_dir /nonexistent does not exist; expected the directory of prediction .lines.txt files\n"
    err = _culane_error(["--pred-dir", str(pred), "--gt-dir", "/nonexistent", "--list", str(lst)], capsys)
    assert "gt_dir /nonexistent does not exist; expected the directory of ground-truth .lines.txt files" in err
    err = _culane_error(["--pred-dir", str(lst), "--gt-dir", str(gt), "--list", str(lst)], capsys)
    assert f"pred_dir {lst} is not a directory" in err
    # an existing directory holding none of the list's predictions: a wrong --pred-dir, not all-FN
    err = _culane_error(["--pred-dir", str(tmp_path), "--gt-dir", str(gt), "--list", str(lst)], capsys)
    assert f"pred_dir {tmp_path} has no prediction file for any of the 2 image paths of {lst}" in err
    assert f"looked for {tmp_path / 'driver_1/05/a.lines.txt'}" in err
    # and a GT tree the list does not match
    err = _culane_error(["--pred-dir", str(pred), "--gt-dir", str(tmp_path), "--list", str(lst)], capsys)
    assert f"the list {lst} and gt_dir {tmp_path} do not match" in err
    assert f"(first entry '/driver_1/05/a.jpg': looked for {tmp_path / 'driver_1/05/a.lines.txt'})" in err


@pytest.mark.parametrize("text, message", [
    ("", "has no image paths; expected one image path per line"),
    ("\n  \n", "has no image paths; expected one image path per line"),
    ("/driver_1/05/a.jpg\n\\driver_1\\05\\b.jpg\n", ":2: image path '\\\\driver_1\\\\05\\\\b.jpg' has backslashes"),
    ("/driver_1/05/a.jpg /laneseg/driver_1/05/a.png 1 1 1 1\n",
     ":1: expected one image path per line, got 6 columns '/driver_1/05/a.jpg /laneseg/driver_1/05/a.png 1 1 1 1' "
     "(a train_gt-style list?"),
])
def test_bad_list_files_name_the_line(tree, tmp_path, capsys, text, message) -> None:
    pred, gt, _ = tree
    lst = tmp_path / "bad_list.txt"
    lst.write_text(text)
    err = _culane_error(["--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(lst)], capsys)
    assert f"{lst}" in err
    assert message in err


@pytest.mark.parametrize("iou", ["1.5", "-1", "0", "1", "nan"])
def test_iou_outside_zero_one_is_refused(tree, capsys, iou) -> None:
    pred, gt, lst = tree
    err = _culane_error(["--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(lst), "--iou", iou], capsys)
    assert "iou_threshold (--iou) must be a number between 0 and 1 (exclusive; official: 0.5)" in err


def test_missing_prediction_for_some_images_still_counts_as_no_lanes(tree) -> None:
    pred, gt, lst = tree  # b has no prediction file: its GT lane is an FN, as officially
    lst.write_text("/driver_1/05/b.jpg\n/driver_1/05/a.jpg\r\n")  # CRLF line ends are fine
    res = evaluate_culane_dirs(str(pred), str(gt), str(lst))
    assert (res["TP"], res["FP"], res["FN"]) == (1, 1, 2)
