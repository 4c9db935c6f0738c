"""The scoring commands stay light (no torch), the package exports lazily, and CULane workers agree."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import lanevil_train.metrics as metrics
from lanevil_train.metrics import evaluate_culane_dirs
from lanevil_train.metrics.__main__ import main
from lanevil_train.metrics.culane_files import lines_file_path, worker_count

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "torchmetrics", "torchvision", "pytorch_lightning", "lightning", "timm", "sklearn")

# Runs `python -m lanevil_train.metrics ARGS` in this interpreter (runpy, as -m does), then reports which
# top-level packages it imported.
PROBE = """
import json, runpy, sys
args = json.loads(sys.argv[1])
sys.argv = ["lanevil_train.metrics", *args]
code = 0
try:
    runpy.run_module("lanevil_train.metrics", run_name="__main__", alter_sys=True)
except SystemExit as e:
    code = e.code
print(json.dumps({"code": code, "top": sorted({m.split(".")[0] for m in sys.modules})}))
"""


def _probe(args: list[str]) -> tuple[dict, set[str]]:
    """(the command's JSON result, the top-level modules it imported) of one fresh process."""
    res = subprocess.run([sys.executable, "-c", PROBE, json.dumps(args)], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    report = json.loads(lines[-1])
    assert report["code"] == 0, res.stderr
    return json.loads(lines[-2]), set(report["top"])


def _tusimple_files(tmp_path: Path) -> tuple[Path, Path]:
    ys = list(range(160, 720, 10))
    gt = {"lanes": [[300] * 56, [-2] * 10 + [700] * 46], "h_samples": ys, "raw_file": "clips/a/20.jpg"}
    pred = {"lanes": [[304.5] * 56, [-2] * 12 + [690] * 44], "raw_file": "clips/a/20.jpg", "run_time": 5}
    (tmp_path / "gt.json").write_text(json.dumps(gt) + "\n")
    (tmp_path / "pred.json").write_text(json.dumps(pred) + "\n")
    return tmp_path / "pred.json", tmp_path / "gt.json"


def _culane_tree(tmp_path: Path, n: int = 24) -> tuple[Path, Path, Path]:
    """n images: 3 GT lanes each; predictions shifted by 0..60 px so some match and some do not."""
    rng = np.random.default_rng(5)
    gt_dir, pred_dir, names = tmp_path / "gt", tmp_path / "pred", []
    for i in range(n):
        name = f"/driver_1/v{i % 3}.MP4/{i:05d}.jpg"
        gts, preds = [], []
        for k in range(3):
            ys = np.arange(589.0, 300.0, -10.0)
            xs = 300 + 500 * k + (0.8 - 0.6 * k) * (589 - ys) + rng.normal(0, 1, ys.size)
            gts.append(np.stack([xs, ys], 1))
            preds.append(gts[-1] + [rng.uniform(0, 60), 0])
        for root, lanes in ((gt_dir, gts), (pred_dir, preds)):
            path = root / lines_file_path(name)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("".join(" ".join(f"{x:.2f} {y:.0f}" for x, y in lane) + "\n" for lane in lanes))
        names.append(name)
    lst = tmp_path / "list.txt"
    lst.write_text("\n".join(names) + "\n")
    return pred_dir, gt_dir, lst


def test_tusimple_command_imports_numpy_only(tmp_path: Path) -> None:
    pred, gt = _tusimple_files(tmp_path)
    result, top = _probe(["tusimple", "--pred", str(pred), "--gt", str(gt)])
    assert result["Accuracy"] == pytest.approx((1 + 54 / 56) / 2)  # 2 rows where only the GT has a point
    assert "numpy" in top
    assert not top & {*HEAVY, "cv2", "scipy"}, top & {*HEAVY, "cv2", "scipy"}


def test_culane_command_imports_no_torch(tmp_path: Path) -> None:
    pred, gt, lst = _culane_tree(tmp_path, n=4)
    result, top = _probe(["culane", "--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(lst)])
    assert result["TP"] + result["FN"] == 12
    assert {"numpy", "cv2"} <= top
    assert not top & set(HEAVY), top & set(HEAVY)


def test_package_import_is_lazy_and_exports_everything() -> None:
    code = ("import sys, lanevil_train.metrics as m; before = 'torch' in sys.modules; m.tusimple_summary; "
            "mid = 'torch' in sys.modules; m.TuSimpleMetric; print(before, mid, 'torch' in sys.modules)")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.stdout.split() == ["False", "False", "True"], res.stderr
    for name in metrics.__all__:
        assert getattr(metrics, name).__name__ == name
    assert set(metrics.__all__) <= set(dir(metrics))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        metrics.nope  # noqa: B018


def test_culane_workers_give_the_same_counts(tmp_path: Path) -> None:
    pred, gt, lst = _culane_tree(tmp_path)
    one = evaluate_culane_dirs(str(pred), str(gt), str(lst), workers=1)
    two = evaluate_culane_dirs(str(pred), str(gt), str(lst), workers=2)
    assert one == two
    assert one["TP"] > 10 and one["FP"] > 5 and one["TP"] + one["FN"] == 72


def test_culane_cli_workers_flag(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    pred, gt, lst = _culane_tree(tmp_path, n=6)
    args = ["culane", "--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(lst)]
    assert main(args + ["--workers", "1"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first == evaluate_culane_dirs(str(pred), str(gt), str(lst))
    assert main(args + ["--workers", "0"]) == 1
    assert "workers must be >= 1" in capsys.readouterr().err


def test_worker_count_and_lines_path() -> None:
    assert worker_count(1, 10_000) == 1
    assert worker_count(8, 3) == 3  # never more processes than images
    assert worker_count(None, 10) == 1  # short lists stay in this process
    assert 1 <= worker_count(None, 100_000)
    with pytest.raises(ValueError):
        worker_count(0, 10)
    assert lines_file_path("/driver_23_30frame/05151649_0422.MP4/00000.jpg") == \
        "driver_23_30frame/05151649_0422.MP4/00000.lines.txt"
    assert lines_file_path("a/b.MP4/00000\n") == "a/b.MP4/00000.lines.txt"  # no extension: keep the name


def test_tusimple_cli_non_finite_ground_truth(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    pred, gt = _tusimple_files(tmp_path)
    gt.write_text(gt.read_text().replace("[300, 300, 300", "[300, Infinity, 300", 1))
    assert main(["tusimple", "--pred", str(pred), "--gt", str(gt)]) == 1
    err = capsys.readouterr().err
    assert err == (f"error: {gt}:1: ground truth lane 0 of raw_file 'clips/a/20.jpg' has a non-finite x (inf) at "
                   f"h_sample index 1 (y = 170); expected a finite x in pixels, or -2 for 'no point'\n")


@pytest.mark.parametrize("workers", ["1", "2"])
def test_culane_cli_non_finite_prediction(tmp_path: Path, capsys: pytest.CaptureFixture, workers: str) -> None:
    """The message names file, line, lane and side, also when a worker process reads the file."""
    pred, gt, lst = _culane_tree(tmp_path)
    bad = pred / lines_file_path(lst.read_text().splitlines()[17])
    lines = bad.read_text().splitlines()
    lines[2] = lines[2].replace(" ", " nan ", 1)
    bad.write_text("\n".join(lines) + "\n")
    args = ["culane", "--pred-dir", str(pred), "--gt-dir", str(gt), "--list", str(lst), "--workers", workers]
    assert main(args) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == (f"error: {bad}:3: prediction lane 2 has a non-finite coordinate 'nan'; "
                            f"expected finite pixel numbers 'x y x y ...'\n")
