"""report.html (report/page/): built from constructed records and table rows, read back with html.parser: the
tables' cells are main.json's numbers, headers are grouped, every image exists, nothing points elsewhere, the
gallery shows the largest drops, task.html=false writes no page."""

from __future__ import annotations

import json
import math
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest

from lanevil_train.report import page as page_module
from lanevil_train.report.page import FILES, PAGE, gallery_picks, write_robustness_page
from lanevil_train.report.robustness import write_report
from lanevil_train.report.specs import LANE_SPEC, record_set
from tests.report.test_robustness import RECORDS, rec


class Parsed(HTMLParser):
    """The page as lists: tags with their attributes, tables by id (header rows and body rows of cells)."""

    def __init__(self, text: str):
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.tables: dict[str, dict] = {}
        self._table = None
        self._part = None
        self._row = None
        self._cell = None
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        self.tags.append((tag, attrs))
        if tag == "table":
            self._table = self.tables.setdefault(attrs.get("id"), {"head": [], "body": []})
        elif tag in ("thead", "tbody") and self._table is not None:
            self._part = "head" if tag == "thead" else "body"
        elif tag == "tr" and self._table is not None:
            self._row = []
            self._table[self._part].append(self._row)
        elif tag in ("td", "th") and self._row is not None:
            self._cell = {"attrs": attrs, "text": ""}
            self._row.append(self._cell)

    def handle_endtag(self, tag):
        if tag == "table":
            self._table = None
        elif tag in ("td", "th"):
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell["text"] += data


def _keyed(records):
    return [{**r, "key": f"{r['model']}/{r['case_id']}/{r['illusion']}_s{r['severity']}"} for r in records]


def _with_images(folder: Path, records):
    """A small image file per record (its own grey level), one true and one predicted lane each."""
    out = []
    for i, r in enumerate(records):
        path = folder / f"img{i}.png"
        cv2.imwrite(str(path), np.full((36, 64, 3), 40 + 10 * i, np.uint8))
        out.append({**r, "image": str(path), "gt_lanes": [[[10, 35], [20, 0]]], "pred_lanes": [[[50, 35], [40, 0]]]})
    return out


def _run(folder: Path, records, **kwargs) -> Path:
    """A run folder as evaluate leaves it: per_image.jsonl, write_report's tables and plots, report.html."""
    folder.mkdir(parents=True, exist_ok=True)
    results = folder / "per_image.jsonl"
    results.write_text("".join(json.dumps(r) + "\n" for r in records))
    write_report(records, folder, baseline="A")
    return write_robustness_page(folder, [results], **kwargs)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    folder = tmp_path_factory.mktemp("run")
    records = _with_images(folder, _keyed(RECORDS))
    path = _run(folder, records)
    return folder, path, Parsed(path.read_text(encoding="utf-8"))


def test_main_table_cells_equal_main_json(built):
    folder, _, parsed = built
    main = {row["model"]: row for row in json.loads((folder / "main.json").read_text())}
    table = parsed.tables["table-main"]
    checked = 0
    for row in table["body"]:
        model = row[0]["text"]
        for cell in row:
            key = cell["attrs"].get("data-key")
            if key is None:
                continue
            want, got = main[model][key], float(cell["attrs"]["data-value"])
            assert (math.isnan(want) and math.isnan(got)) or got == want, (model, key)
            checked += 1
    # 2 models x (2 categories + average) x 2 scores (Accuracy, F1) x Perturbed / Original / Gap
    assert checked == 2 * 3 * 2 * 3
    assert [r[1]["text"] for r in table["body"]] == ["shadow", "reflection", "average"] * 2


def test_headers_are_grouped_perturbed_original_gap(built):
    _, _, parsed = built
    head = parsed.tables["table-main"]["head"]
    assert len(head) == 2
    groups = [(c["text"], c["attrs"].get("colspan")) for c in head[0] if c["attrs"].get("colspan")]
    assert groups == [("Accuracy", "3"), ("F1", "3")]
    assert [c["attrs"].get("rowspan") for c in head[0][:2]] == ["2", "2"]
    assert [c["text"] for c in head[1]] == ["Perturbed", "Original", "Gap"] * 2
    # every leaf header names its body column, for sorting
    cols = sorted(int(c["attrs"]["data-col"]) for r in head for c in r if "data-col" in c["attrs"])
    assert cols == list(range(len(parsed.tables["table-main"]["body"][0])))
    severity = parsed.tables["table-per_severity"]["head"]
    assert [c["text"] for c in severity[1]][:3] == ["Perturbed", "Original", "Gap"]


def test_gap_cells_coloured_by_sign(built):
    _, _, parsed = built
    gaps = [c for r in parsed.tables["table-main"]["body"] for c in r if "gap" in c["attrs"].get("class", "")]
    assert gaps
    for cell in gaps:
        value = float(cell["attrs"]["data-value"])
        classes = cell["attrs"]["class"].split()
        if value < 0:
            assert "worse" in classes and "214, 39, 40" in cell["attrs"]["style"]
        elif value > 0:
            assert "better" in classes and "31, 119, 180" in cell["attrs"]["style"]


def test_images_exist_and_nothing_points_elsewhere(built):
    folder, _, parsed = built
    sources = [a["src"] for tag, a in parsed.tags if tag == "img"]
    assert any(s.startswith(f"{FILES}/") for s in sources) and "gap_heatmap.png" in sources
    for src in sources:
        assert (folder / src).is_file(), src
    for tag, attrs in parsed.tags:
        for name in ("src", "href"):
            value = attrs.get(name)
            if value is not None:
                assert not value.startswith(("http:", "https:", "//")), (tag, value)
        assert not (tag == "link" or (tag == "script" and "src" in attrs))
    assert all(tag != "img" or a["src"] != "worst_cases.png" for tag, a in parsed.tags)


def test_header_and_sortable_tables(built):
    _, path, parsed = built
    text = path.read_text()
    import lanevil_train

    assert f"<dd>{lanevil_train.__version__}</dd>" in text and "<dt>command</dt>" in text
    tables = [a for tag, a in parsed.tags if tag == "table"]
    assert {"table-main", "table-per_type", "table-per_severity", "table-relative"} <= {a["id"] for a in tables}
    assert all("sortable" in a["class"] for a in tables)
    assert "addEventListener('click'" in text


def test_gallery_picks_the_largest_drops(tmp_path):
    """Per illusion, one image per case (its largest drop), largest first; a case the illusion did not hurt is
    left out. fence_shadow drops: c1 s1 .9-.5 = .4, s2 .9-.1 = .8 (c1's pick); c2 s1 .6-.5 = .1; c3 .7-.7 = 0."""
    fs = "fence_shadow"
    records = _keyed([rec("A", "c1", 0, 0.9, 0, 0), rec("A", "c2", 0, 0.6, 0, 0), rec("A", "c3", 0, 0.7, 0, 0),
                      rec("A", "c1", 1, 0.5, 0, 0, fs), rec("A", "c1", 2, 0.1, 0, 0, fs),
                      rec("A", "c2", 1, 0.5, 0, 0, fs), rec("A", "c3", 1, 0.7, 0, 0, fs),
                      rec("A", "c2", 2, 0.2, 0, 0, "sunlight_reflection")])
    picks = gallery_picks(record_set(records, LANE_SPEC), per_type=4)["A"]
    assert [(p.perturbed["case_id"], p.perturbed["severity"]) for p in picks[fs]] == [("c1", 2), ("c2", 1)]
    assert picks[fs][0].drop == pytest.approx(80.0) and picks[fs][0].clean["case_id"] == "c1"
    assert [p.perturbed["case_id"] for p in picks["sunlight_reflection"]] == ["c2"]
    assert [p.perturbed["case_id"] for p in gallery_picks(record_set(records, LANE_SPEC), 1)["A"][fs]] == ["c1"]
    parsed = Parsed(_run(tmp_path, _with_images(tmp_path, records)).read_text())
    figures = [a for tag, a in parsed.tags if tag == "figure" and "pair" in a.get("class", "")]
    assert [(f["data-illusion"], f["data-case"], f["data-severity"]) for f in figures] == \
        [(fs, "c1", "2"), (fs, "c2", "1"), ("sunlight_reflection", "c2", "2")]
    assert float(figures[0]["data-drop"]) == pytest.approx(80.0)
    jpegs = sorted(p.name for p in (tmp_path / FILES).glob("*.jpg"))
    assert len(jpegs) == 5  # c1 and c2 originals shared by both types, three perturbed images
    assert cv2.imread(str(tmp_path / FILES / jpegs[0])).shape[:2] == (36, 64)  # small images are not enlarged


def test_rerun_rewrites_page_and_drops_stale_images(tmp_path):
    records = _with_images(tmp_path, _keyed(RECORDS))
    _run(tmp_path, records)
    stale = tmp_path / FILES / "gone-0123456789.jpg"
    stale.write_bytes(b"old")
    write_robustness_page(tmp_path, [tmp_path / "per_image.jsonl"], per_type=1)
    assert not stale.exists()
    parsed = Parsed((tmp_path / PAGE).read_text())
    shown = {a["src"].split("/", 1)[1] for tag, a in parsed.tags if tag == "img" and a["src"].startswith(FILES)}
    assert shown == {p.name for p in (tmp_path / FILES).glob("*.jpg")}
    assert not list(tmp_path.glob(".*.partial"))


def test_on_the_fly_suite_images_rendered_again(tmp_path):
    """Records without image files (an on-the-fly suite) are drawn from per_image.suite.json's suite."""
    from lanevil_train.data.suites import SyntheticIllusionSuite

    suite = SyntheticIllusionSuite(1, 1000000, (72, 128), ["fence_shadow"], (2,))
    keys = [suite.item_key(i) for i in range(len(suite))]
    base = {"model": "A", "dataset": "synthetic-illusions", "case_id": "sim-1000000-f0", "fp": 0.0, "fn": 0.0,
            "image": None, "gt_lanes": [[[20, 71], [60, 30]]], "pred_lanes": [[[100, 71], [70, 30]]]}
    records = [{**base, "key": keys[0], "severity": 0, "accuracy": 1.0},
               {**base, "key": keys[1], "severity": 2, "accuracy": 0.25, "illusion": "fence_shadow"}]
    (tmp_path / "per_image.suite.json").write_text(json.dumps(suite.description()))
    parsed = Parsed(_run(tmp_path, records).read_text())
    sources = [a["src"] for tag, a in parsed.tags if tag == "img" and a["src"].startswith(FILES)]
    assert len(sources) == 2
    rendered = cv2.cvtColor(suite[1]["image"], cv2.COLOR_RGB2BGR).astype(float)
    drawn = cv2.imread(str(tmp_path / sources[1])).astype(float)
    assert drawn.shape == rendered.shape
    assert np.abs(drawn - rendered)[:25].mean() < 12  # the suite's image (above the drawn lanes), as a JPEG


def test_write_results_html_flag(tmp_path):
    """write_results (what task=evaluate, a training run's suite and task=report call) writes the page unless
    html=False (task.html=false)."""
    from lanevil_train.evaluation.results import write_results

    for html, folder in ((False, tmp_path / "off"), (True, tmp_path / "on")):
        folder.mkdir()
        results = folder / "per_image.jsonl"
        results.write_text("".join(json.dumps(r) + "\n" for r in _keyed(RECORDS)))
        write_results([results], folder, html=html)
        assert (folder / "report.md").is_file()
        assert (folder / PAGE).is_file() == html
        assert (folder / FILES).exists() is False  # no image files: no gallery


def test_task_html_rule():
    from lanevil_train.tasks.config_check.table import RULES

    assert RULES["task.html"].test(True) is None and RULES["task.html"].test(False) is None
    assert RULES["task.html"].test("yes") is not None


def test_compare_page_gains_with_intervals(tmp_path):
    from lanevil_train.report.defenses import defense_gain, defense_scores

    records = {"none": [r for r in RECORDS if r["model"] == "A"],
               "aam": [{**r, "model": "A+aam"} for r in RECORDS if r["model"] == "B"]}
    scores = defense_scores(records)
    gains = defense_gain(scores)
    for row in gains:
        row.update({"Accuracy/low": row["Accuracy/gain"] - 1.0, "Accuracy/high": row["Accuracy/gain"] + 2.0,
                    "Accuracy/distinguishable": True})
    run = tmp_path / "runs" / "aam"
    (run / "robustness").mkdir(parents=True)
    (run / "robustness" / PAGE).write_text("<html></html>")
    path = page_module.write_compare_page(tmp_path, scores, gains, LANE_SPEC, {"none": {0: str(tmp_path / "x")},
                                                                               "aam": {0: str(run)}})
    parsed = Parsed(path.read_text())
    table = parsed.tables["table-gain-Accuracy"]
    want = {r["category"]: r for r in gains}
    header = [c["text"] for c in table["head"][0]]
    row = table["body"][0]
    assert row[0]["text"] == "aam"
    for name, cell in zip(header[1:], row[1:]):
        assert float(cell["attrs"]["data-value"]) == want[name]["Accuracy/gain"]
        assert float(cell["attrs"]["data-low"]) == want[name]["Accuracy/low"]
        assert float(cell["attrs"]["data-high"]) == want[name]["Accuracy/high"]
    links = [a["href"] for tag, a in parsed.tags if tag == "a" and not a["href"].startswith("#")]
    assert links == ["runs/aam/robustness/report.html"]
    scores_table = parsed.tables["table-defense_scores"]
    cells = {c["attrs"]["data-key"]: float(c["attrs"]["data-value"]) for c in scores_table["body"][0]
             if "data-value" in c["attrs"]}
    assert cells["average/Accuracy"] == scores[0]["average/Accuracy"]


def _answer(case, qa, sev, score, answer, illusion=None):
    clip = f"{case}-{'clean' if sev == 0 else f's{sev}'}"
    return {"spec": "vqa", "model": "V", "dataset": "clips", "case_id": case, "qa_id": qa, "clip_id": clip,
            "key": f"{clip}/{qa}", "severity": sev, "illusion": illusion,
            "category": "shadow" if illusion else None, "qa_category": "perception", "qa_type": "yes_no",
            "segment": "before", "question": f"Is there a lane? <{qa}>", "reference": "Yes.", "answer": answer,
            "minilm_score": score, "correct": int(score > 50)}


def test_vlm_page_worst_answers_beside_frames(tmp_path):
    """The VLM page: its tables, and the answers the illusion hurt most with both clips' frames (from the clip
    files per_answer.suite.json names), worst first; an answer not hurt is left out."""
    fs = "fence_shadow"
    records = [_answer("c1", "q1", 0, 90.0, "Yes."), _answer("c1", "q2", 0, 80.0, "Yes."),
               _answer("c2", "q1", 0, 70.0, "Yes."),
               _answer("c1", "q1", 3, 20.0, "No.", fs), _answer("c1", "q2", 3, 60.0, "Maybe.", fs),
               _answer("c2", "q1", 3, 70.0, "Yes.", fs)]
    frames = {}
    for clip in ("c1-clean", "c1-s3", "c2-clean", "c2-s3"):
        paths = []
        for i in range(5):
            path = tmp_path / "clips" / f"{clip}-{i}.png"
            path.parent.mkdir(exist_ok=True)
            cv2.imwrite(str(path), np.full((36, 64, 3), 30 * i, np.uint8))
            paths.append(str(path))
        frames[clip] = paths
    out = tmp_path / "run"
    out.mkdir()
    results = out / "per_answer.jsonl"
    results.write_text("".join(json.dumps(r) + "\n" for r in records))
    (out / "per_answer.suite.json").write_text(json.dumps({"suite": "clip_frames", "frames": frames}))
    write_report(records, out)
    parsed = Parsed(page_module.write_vlm_page(out, [results]).read_text())
    main = json.loads((out / "main.json").read_text())[0]
    cells = [c for r in parsed.tables["table-main"]["body"] for c in r if "data-key" in c["attrs"]]
    assert cells and all(float(c["attrs"]["data-value"]) == main[c["attrs"]["data-key"]] for c in cells)
    figures = [a for tag, a in parsed.tags if tag == "figure" and "answer" in a.get("class", "")]
    assert [(f["data-case"], f["data-qa"], float(f["data-drop"])) for f in figures] == [("c1", "q1", 70.0),
                                                                                        ("c1", "q2", 20.0)]
    sources = [a["src"] for tag, a in parsed.tags if tag == "img" and a["src"].startswith(FILES)]
    assert len(sources) == 2 * 2 * page_module.STRIP_FRAMES
    assert all((out / src).is_file() for src in sources)


TRACE = [{"t": t / 10, "s": float(t), "deviation": 0.01 * t} for t in range(30)]  # one trace for every run


def closed_loop_runs(cases, categories: dict[str, str], hits: dict[str, set]) -> list[dict]:
    """runs.jsonl-style records of a closed loop: per case and illusion (its category) a clean and a perturbed run,
    the perturbed one an attack success where `hits[illusion]` holds the case."""
    records = []
    for case in cases:
        for illusion, category in categories.items():
            for perturbed in (False, True):
                hit = perturbed and case in hits[illusion]
                records.append({"model": "M", "key": f"{case}/{illusion}/{int(perturbed)}", "case_id": case,
                                "illusion": illusion, "category": category, "severity": 3 if perturbed else 0,
                                "perturbed": perturbed, "repeat": 0, "success": hit, "twin_success": hit,
                                "max_deviation_m": 0.5 if hit else 0.1, "first_departure_s": 1.5 if hit else None,
                                "departures_per_km": 2.0 if hit else 0.0, "collision": False, "entry_s": 0.5,
                                "region_m": [5.0, 15.0]})
    return records


def test_closed_loop_page_rates_with_intervals(tmp_path):
    """The closed-loop page: asr_by_category.json's ASR in its cells, the Wilson interval folded into each rate's
    cell, time metrics kept, the plots shown from disk."""
    from lanevil_train.report.closed_loop import write_closed_loop_report

    hits = {"fence_shadow": {"c1"}, "vehicle": {"c1"}}
    categories = {"fence_shadow": "shadow", "vehicle": "traffic_obstruction"}
    write_closed_loop_report(closed_loop_runs(("c1", "c2"), categories, hits), lambda record: TRACE, tmp_path,
                             {"cases": 2})
    parsed = Parsed(page_module.write_closed_loop_page(tmp_path, {"cases": 2}).read_text())
    rows = json.loads((tmp_path / "asr_by_category.json").read_text())
    table = parsed.tables["table-asr_by_category"]
    labels = [c["text"] for c in table["head"][0]]
    assert "95% CI" not in labels and "time to departure (s)" in labels
    for row, want in zip(table["body"], rows):
        cell = row[labels.index("ASR (%)")]
        assert float(cell["attrs"]["data-value"]) == want["ASR (%)"]
        low, high = json.loads(want["95% CI"])
        assert float(cell["attrs"]["data-low"]) == low and float(cell["attrs"]["data-high"]) == high
    sources = [a["src"] for tag, a in parsed.tags if tag == "img"]
    assert sources == ["asr.png", "deviation.png"] and all((tmp_path / s).is_file() for s in sources)
