"""CULane as leaderboards report it: F1@50, F1@75, mF1 from one matching per image, and the nine category lists."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lanevil_train.metrics import (
    culane_image_counts,
    culane_image_counts_multi,
    culane_leaderboard_scores,
    culane_sweep_summary,
    evaluate_culane_dirs,
)
from lanevil_train.metrics.__main__ import main
from lanevil_train.metrics.culane import MF1_THRESHOLDS, culane_matched_ious
from lanevil_train.metrics.culane_files import CATEGORIES

# Vertical 2-point lanes, 30 px wide on 1640x590: a prediction shifted by 3 px has IoU 0.822 (a TP at 0.50..0.80),
# by 8 px IoU 0.587 (a TP at 0.50 and 0.55 only); an exact copy IoU 1 (a TP at every threshold).
G1, G2, G3 = ([[x, 580.0], [x, 100.0]] for x in (300.0, 800.0, 1300.0))
SPURIOUS = [[1600.0, 580.0], [1600.0, 300.0]]


def shifted(lane: list, dx: float) -> list:
    return [[x + dx, y] for x, y in lane]


NORMAL_PRED, NORMAL_GT = [G1, shifted(G2, 3), shifted(G3, 8), SPURIOUS], [G1, G2, G3]
# TP of the "normal" image at 0.50, 0.55, ..., 0.95: 3 lanes, then the 8 px one drops out, then the 3 px one
NORMAL_TP = [3, 3, 2, 2, 2, 2, 2, 1, 1, 1]


def test_matched_ious_and_counts_at_every_threshold_by_hand() -> None:
    ious = sorted(culane_matched_ious(NORMAL_PRED, NORMAL_GT))
    assert ious[0] == pytest.approx(0.5870, abs=1e-4) and ious[1] == pytest.approx(0.8221, abs=1e-4)
    assert ious[2] == 1.0
    counts = culane_image_counts_multi(NORMAL_PRED, NORMAL_GT)
    assert [c[0] for c in counts] == NORMAL_TP
    assert counts[0] == (3, 1, 0) and counts[-1] == (1, 3, 2)  # FP = 4 predicted - TP, FN = 3 GT - TP
    totals = dict(zip(MF1_THRESHOLDS, counts))
    scores = culane_leaderboard_scores(totals)
    # F1 = 2 TP / (predicted + GT) = 2 TP / 7
    assert scores["F1@50"] == pytest.approx(6 / 7) and scores["F1@75"] == pytest.approx(4 / 7)
    assert scores["mF1"] == pytest.approx(2 * sum(NORMAL_TP) / 70)  # 38 / 70
    summary = culane_sweep_summary(totals)  # and precision / recall at IoU 0.5
    assert (summary["TP"], summary["Precision"], summary["Recall"]) == (3, 0.75, 1.0)
    assert summary["mF1"] == scores["mF1"]
    with pytest.raises(ValueError, match=r"lack the IoU thresholds \[0.95\]"):
        culane_leaderboard_scores({t: c for t, c in totals.items() if t != 0.95})


def test_one_pass_equals_one_run_per_threshold() -> None:
    rng = np.random.default_rng(7)
    for _ in range(15):
        gt = [np.stack([rng.uniform(100, 1500) + np.arange(6) * rng.normal(0, 20), 580 - 60 * np.arange(6)], 1)
              for _ in range(rng.integers(0, 4))]
        pred = [g + [rng.normal(0, 6), 0] + rng.normal(0, 2, g.shape) for g in gt if rng.random() < 0.8]
        pred += [np.array([[rng.uniform(0, 1640), 580.0], [rng.uniform(0, 1640), 300.0]])] * int(rng.random() < 0.3)
        assert culane_image_counts_multi(pred, gt) == [culane_image_counts(pred, gt, iou_threshold=t)
                                                       for t in MF1_THRESHOLDS]
    # other canvases and lane widths (CurveLanes' kind) give the same equality
    small = [np.array([[10.0, 200.0], [60.0, 20.0], [90.0, 0.0]])]
    moved = [small[0] + [2, 0]]
    assert culane_image_counts_multi(moved, small, 224, 224, 5, (0.3, 0.5)) == \
        [culane_image_counts(moved, small, 224, 224, 5, t) for t in (0.3, 0.5)]


# One image per category: normal is the image above, six are exact copies of one lane, cross has no GT lane and two
# predictions, night has one GT lane and an empty prediction file.
EXACT = [[[700.0, 580.0], [650.0, 200.0]]]
IMAGES = {"normal": (NORMAL_PRED, NORMAL_GT), "cross": ([G1, SPURIOUS], []), "night": ([], [G2]),
          **{name: (EXACT, EXACT) for name in ("crowd", "hlight", "shadow", "noline", "arrow", "curve")}}


def _write(path: Path, lanes: list) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{x:.3f} {y:.3f}" for x, y in lane) + "\n" for lane in lanes))


@pytest.fixture()
def culane_set(tmp_path: Path) -> tuple[Path, Path, Path, Path]:
    """(pred dir, GT root, list/test.txt, list/test_split/) of the nine one-image categories."""
    root, pred = tmp_path / "culane", tmp_path / "pred"
    split = root / "list" / "test_split"
    split.mkdir(parents=True)
    names = []
    for category, filename in CATEGORIES:
        name = f"/driver_1/{category}.MP4/00000.jpg"
        p, g = IMAGES[category]
        _write(pred / f"driver_1/{category}.MP4/00000.lines.txt", p)
        _write(root / f"driver_1/{category}.MP4/00000.lines.txt", g)
        (split / filename).write_text(name + "\n")
        names.append(name)
    test = root / "list" / "test.txt"
    test.write_text("".join(n + "\n" for n in names))
    return pred, root, test, split


def test_categories_by_hand(culane_set: tuple[Path, Path, Path, Path]) -> None:
    pred, root, test, split = culane_set
    res = evaluate_culane_dirs(str(pred), str(root), str(test), categories=str(split), workers=1)
    cats = res["categories"]
    assert list(cats) == [name for name, _ in CATEGORIES] + ["total"]
    assert cats["normal"]["F1@50"] == pytest.approx(6 / 7) and cats["normal"]["F1@75"] == pytest.approx(4 / 7)
    assert cats["normal"]["mF1"] == pytest.approx(38 / 70)
    assert all(cats[c]["F1@50"] == cats[c]["mF1"] == 1.0 for c in ("crowd", "hlight", "shadow", "noline", "arrow"))
    assert cats["cross"] == {"images": 1, "FP": 2}  # no GT lanes: the FP count only
    assert (cats["night"]["TP"], cats["night"]["FN"], cats["night"]["F1@50"]) == (0, 1, 0.0)
    # total: 12 predicted, 10 GT lanes, TP(t) = normal's + 6 exact copies
    assert (cats["total"]["TP"], cats["total"]["FP"], cats["total"]["FN"]) == (9, 3, 1)
    assert res["F1@50"] == cats["total"]["F1@50"] == pytest.approx(18 / 22)
    assert res["F1@75"] == pytest.approx(16 / 22)
    assert res["mF1"] == pytest.approx(2 * (sum(NORMAL_TP) + 60) / 220)
    assert res["images"] == 9 and (res["TP"], res["FP"], res["FN"]) == (9, 3, 1)


def test_categories_equal_one_run_per_list(culane_set: tuple[Path, Path, Path, Path]) -> None:
    """What the official scripts do (one evaluator run per category list) equals the one-pass category rows."""
    pred, root, test, split = culane_set
    cats = evaluate_culane_dirs(str(pred), str(root), str(test), categories=str(split), workers=1)["categories"]
    for category, filename in CATEGORIES:
        alone = evaluate_culane_dirs(str(pred), str(root), str(split / filename), workers=1)
        row = cats[category]
        assert alone["FP"] == row["FP"] and alone["images"] == row["images"]
        if category != "cross":
            assert {k: alone[k] for k in ("TP", "FN", "F1@50", "F1@75", "mF1")} == \
                {k: row[k] for k in ("TP", "FN", "F1@50", "F1@75", "mF1")}


def test_cli_table_and_json(culane_set: tuple[Path, Path, Path, Path], capsys: pytest.CaptureFixture) -> None:
    pred, root, test, split = culane_set
    args = ["culane", "--pred-dir", str(pred), "--gt-dir", str(root), "--list", str(test), "--categories", str(split)]
    assert main(args + ["--table"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| list | images | F1@50 | F1@75 | mF1 | FP |"
    assert "| normal | 1 | 85.71 | 57.14 | 54.29 | 1 |" in lines and "| cross | 1 | - | - | - | 2 |" in lines
    assert lines[-1] == "| total | 9 | 81.82 | 72.73 | 71.82 | 3 |"
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["categories"]["cross"] == {"images": 1, "FP": 2} and out["mF1"] == pytest.approx(158 / 220)


def test_refusals_name_the_file_and_line(culane_set: tuple[Path, Path, Path, Path],
                                         capsys: pytest.CaptureFixture) -> None:
    pred, root, test, split = culane_set
    run = lambda: evaluate_culane_dirs(str(pred), str(root), str(test), categories=str(split))  # noqa: E731
    night = split / "test8_night.txt"
    night.write_text("/driver_1/night.MP4/00000.jpg\n/driver_9/elsewhere.MP4/00030.jpg\n")
    with pytest.raises(ValueError, match=rf"{night}:2: image '/driver_9/elsewhere.MP4/00030.jpg' is not in the"):
        run()
    night.write_text("/driver_1/night.MP4/00000.jpg\n\n/driver_1/night.MP4/00000.jpg\n")
    with pytest.raises(ValueError, match=rf"{night}:3: .* listed twice \(first at line 1\)"):
        run()
    night.unlink()
    with pytest.raises(FileNotFoundError, match=r"lacks the category list\(s\) test8_night.txt"):
        run()
    assert main(["culane", "--pred-dir", str(pred), "--gt-dir", str(root), "--list", str(test),
                 "--categories", str(split / "nowhere")]) == 1
    assert "--categories" in capsys.readouterr().err


def test_benchmark_set_and_table(tmp_path: Path) -> None:
    """benchmarks/bench_culane_categories.py: its set scores, and its table says equal for equal counts."""
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_culane_categories.py"
    spec = importlib.util.spec_from_file_location("bench_culane_categories", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    pred, test, split = bench.write_set(tmp_path, 18, seed=0)
    assert (split / "test7_cross.txt").read_text().count("\n") == 2
    result, ours, _ = bench.our_counts(tmp_path, pred, test, split)
    assert result["categories"]["cross"]["FP"] == ours["cross"][0.5][1] > 0
    text = bench.table(result, ours, ours)
    assert text.count("| equal |") == 10
    other = {**ours, "night": {t: (0, 0, 0) for t in MF1_THRESHOLDS}}
    assert "| night | 2 |" in text and "DIFFER" in bench.table(result, other, ours)
