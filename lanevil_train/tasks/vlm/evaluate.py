"""task=evaluate for a VLM (model=vlm/<backend>): every QA on every clip variant of a clip suite, answered, scored and
reported in the paper's layout (Perturbed / Original / Gap per illusion category, QA category, type, severity).

    python -m lanevil_train task=evaluate model=vlm/hf model.path=DIR task.suite=synthetic
    python -m lanevil_train task=evaluate model=vlm/openai model.base_url=URL model.name=NAME task.suite=DIR

Answers stream to answers.jsonl, scored records to per_answer.jsonl (both resumable); tables and plots follow.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytorch_lightning as pl
from omegaconf import DictConfig, open_dict

from lanevil_train.evaluation.results import log_results, write_results
from lanevil_train.evaluation.streaming import claim_results
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.report.page import suite_file, write_vlm_page
from lanevil_train.tasks.builders import build_logger, build_split, output_dir
from lanevil_train.tasks.vlm.builders import (
    add_defense_to_report,
    build_defended_vlm,
    build_judge,
    clip_suite,
)
from lanevil_train.vlm.answer_scoring.evaluation import ANSWERS, PER_ANSWER, evaluate_clips
from lanevil_train.vlm.backends.text_only import TextOnlyReader, TextOnlyVLM
from lanevil_train.vlm.base import VLM, BlindVLM
from lanevil_train.vlm.clips.qa_records import QA_CATEGORIES


def run_identity(vlm: VLM, judge, label: dict) -> dict:
    """What makes two VLM evaluations the same: the label, the backend's identity, the judge."""
    return {**{k: str(v) for k, v in label.items()}, **{f"vlm.{k}": v for k, v in vlm.identity().items()},
            "judge": getattr(judge, "name", None)}


def evaluate_vlm(cfg: DictConfig) -> float:
    """Evaluate the VLM; returns its headline score (the judge's, else Language) over the perturbed answers."""
    pl.seed_everything(cfg.seed, workers=True)
    dataset, dataset_name = clip_suite(cfg)  # read and checked before the model is loaded
    reader = text_reader(cfg) if "text" in blind_kinds(cfg) else None  # the text-only baseline: fitted first
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    vlm = build_defended_vlm(cfg)  # defense=pat++ defense.prefix_path=...: the tuned prefix before every question
    judge = build_judge(cfg, out)
    name = cfg.task.label or vlm.name
    results = evaluate_into(vlm, dataset, judge, out, {"model": name, "dataset": dataset_name}, cfg.progress)
    files = [results, *blind_baselines(cfg, vlm, reader, dataset, judge, out, name, dataset_name)]
    value = write_results(files, out, baseline=cfg.task.baseline, html=False)
    from lanevil_train.tasks.cards import suite_plan, vlm_identity, write_evaluation_card

    write_evaluation_card(results, out, vlm_identity(cfg, vlm), suite_plan(dataset), cfg.task.baseline)
    write_gap_intervals(results, out)
    write_visual_reliance(files, out)
    write_drivelm_score(files, out)
    add_defense_to_report(out, vlm)
    write_language_summary(files, out)
    write_worst_answers(results, out)
    if cfg.task.get("html", True) and (out / "report.md").is_file():
        print(f"Report page: {write_vlm_page(out, files)}")
    log_results(build_logger(cfg), out)
    return value


# task.blind: which blind baselines answer the same questions beside the model (true: the grey frames, as before)
BLIND_KINDS = {"false": (), "true": ("grey",), "grey": ("grey",), "text": ("text",), "all": ("grey", "text")}


def blind_kinds(cfg: DictConfig) -> tuple[str, ...]:
    return BLIND_KINDS[str(cfg.task.get("blind") or False).lower()]


def text_reader(cfg: DictConfig) -> TextOnlyReader:
    """The text-only reader fitted on the QA of data.train (question and options only: no frame is rendered),
    checked before any question is asked."""
    train = build_split(cfg, "train")
    if hasattr(train, "plan"):  # a synthetic split: its QA planned from the scenes' truth, with a progress bar
        return TextOnlyReader().fit([qa for qas in train.plan(progress=cfg.progress).values() for qa in qas])
    bases = list(dict.fromkeys(train.clip_meta(i)["base_clip_id"] for i in range(len(train))))
    return TextOnlyReader().fit([qa for base in bases for qa in train.qa_for(base)])


def blind_baselines(cfg: DictConfig, vlm: VLM, reader: TextOnlyReader | None, dataset, judge, out: Path, name: str,
                    dataset_name: str) -> list[Path]:
    """The results files of the blind baselines task.blind asks for, each asked every question the model is: the
    model on grey frames (`<name>-blind`, in out/blind) and the text-only reader (`<name>-text`, in out/text)."""
    files = []
    if "grey" in blind_kinds(cfg):
        files.append(evaluate_into(BlindVLM(vlm), dataset, judge, out / "blind",
                                   {"model": f"{name}-blind", "dataset": dataset_name}, cfg.progress))
    if "text" in blind_kinds(cfg):
        files.append(evaluate_into(TextOnlyVLM(reader, f"{name}-text"), dataset, judge, out / "text",
                                   {"model": f"{name}-text", "dataset": dataset_name}, cfg.progress))
    return files


def evaluate_into(vlm: VLM, dataset, judge, out: Path, label: dict, progress: str) -> Path:
    """evaluate_clips into `out`, after checking that results already there come from this same evaluation; the
    suite's description (per_answer.suite.json: how to render or find its clips' frames) beside the results."""
    identity = run_identity(vlm, judge, label)
    for name in (ANSWERS, PER_ANSWER):
        path = out / name
        claim_results(path, identity, resuming=path.is_file() and path.stat().st_size > 0)
    results = evaluate_clips(vlm, dataset, out, label, judge=judge, progress=progress)
    if hasattr(dataset, "description"):  # where the report page finds the clips' frames (report/page/)
        atomic_write_text(suite_file(results), json.dumps(dataset.description()) + "\n")
    return results


def append_to_report(out: Path, section: str) -> None:
    """Add a markdown section at the end of out/report.md (when it exists)."""
    report = out / "report.md"
    if report.is_file():
        atomic_write_text(report, f"{report.read_text().rstrip()}\n\n{section}")


def write_gap_intervals(results: Path, out: Path) -> Path | None:
    """gap_intervals.json and a section of report.md: the model's yes/no and choice accuracy on perturbed clips
    minus that on the same questions' clean clips, per QA category, with a paired bootstrap 95 % interval over the
    scenes (report/reliance.py gap_rows); None without a closed question."""
    from lanevil_train.evaluation.lane_records import read_records
    from lanevil_train.report.reliance import gap_markdown, gap_rows

    records = read_records(results, keep_lanes=False)
    rows = gap_rows(records, order=QA_CATEGORIES)
    if not rows:
        return None
    section = (f"## The illusions' accuracy Gap of {records[0]['model']}, with intervals\n\n"
               f"Yes/no and choice accuracy (%) on the perturbed clips and on the same questions' clean clips; Gap = "
               f"Perturbed - Original with a paired bootstrap 95 % interval over the scenes (* : it excludes 0).\n\n"
               f"{gap_markdown(rows)}")
    atomic_write_text(out / "gap_intervals.json", json.dumps(rows, indent=1) + "\n")
    append_to_report(out, section)
    return out / "gap_intervals.json"


def write_visual_reliance(results: list[Path], out: Path) -> Path | None:
    """visual_reliance.{json,md} and a section of report.md: the model's (results[0]) yes/no and choice accuracy
    beside its blind baselines' (the other files) and the reliance on the frames with intervals
    (report/reliance.py); None without a baseline."""
    from lanevil_train.evaluation.lane_records import read_records
    from lanevil_train.report.reliance import reliance_markdown, reliance_rows

    if len(results) < 2:
        return None
    model = read_records(results[0], keep_lanes=False)
    baselines = {}
    for path in results[1:]:
        records = read_records(path, keep_lanes=False)
        baselines[records[0]["model"] if records else path.parent.name] = records
    rows = reliance_rows(model, baselines, order=QA_CATEGORIES)
    names = list(baselines)
    section = (f"## Visual reliance: {model[0]['model'] if model else 'the model'} beside its blind baselines\n\n"
               f"Accuracy (%) on every answer (clean and perturbed clips); reliance = the model minus the better "
               f"blind baseline, with a paired bootstrap 95 % interval over the scenes (* : it excludes 0).\n\n"
               f"{reliance_markdown(rows, names)}")
    atomic_write_text(out / "visual_reliance.json", json.dumps(rows, indent=1) + "\n")
    atomic_write_text(out / "visual_reliance.md", f"# {section[3:]}")
    append_to_report(out, section)
    print(section)
    return out / "visual_reliance.md"


def write_drivelm_score(results: list[Path], out: Path) -> Path | None:
    """drivelm_score.json and a section of report.md: DriveLM's challenge score of each model's original and
    perturbed answers and its parts (vlm/answer_scoring/drivelm_score.py); None where no answer has a GPT score (no LLM
    judge)."""
    from lanevil_train.evaluation.lane_records import read_records
    from lanevil_train.report.tables import markdown_table
    from lanevil_train.vlm.answer_scoring.drivelm_score import drivelm_parts

    rows = []
    for path in results:
        records = read_records(path, keep_lanes=False)
        for kind, chosen in (("original", [r for r in records if r["severity"] == 0]),
                             ("perturbed", [r for r in records if r["severity"] != 0])):
            parts = drivelm_parts(chosen)
            if parts is not None:
                rows.append({"model": records[0]["model"], "answers_kind": kind, **parts})
    if not rows:
        return None
    absent = any(row["Match"] is None for row in rows)
    table = markdown_table([{**row, "Match": "absent (0)" if row["Match"] is None else round(row["Match"], 2),
                             **{k: round(row[k], 2) for k in ("GPT", "Language", "Accuracy", "final")}}
                            for row in rows])
    note = (" These clips hold no coordinate question, so match is absent and counted as 0, as DriveLM scores a "
            "submission without it: the final score cannot exceed 80." if absent else "")
    section = ("## DriveLM's challenge score\n\n"
               "final = 0.4 GPT + 0.2 Language + 0.2 match + 0.2 Accuracy (DriveLM's challenge/evaluation.py, here x "
               f"100), from the judge's GPT score, the Language score of every answer and the yes/no and choice "
               f"accuracy.{note}\n\n{table}")
    atomic_write_text(out / "drivelm_score.json", json.dumps(rows, indent=1) + "\n")
    append_to_report(out, section)
    return out / "drivelm_score.json"


def _cell(text: str) -> str:
    """Text as one markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|")


def write_worst_answers(results: Path, out: Path, k: int = 12) -> Path | None:
    """worst_answers.md: the k questions whose answer got most worse under an illusion (by the judge's score,
    else by accuracy), each with its reference, the clean clip's answer and the perturbed clip's; None when no
    answer got worse."""
    from lanevil_train.evaluation.lane_records import read_records
    from lanevil_train.report.page import worst_answer_pairs
    from lanevil_train.report.tables import markdown_table

    field, pairs = worst_answer_pairs(read_records(results, keep_lanes=False), k)
    if not pairs:
        return None
    scale = 100.0 if field == "correct" else 1.0
    rows = [{"model": r["model"], "illusion": f"{r['illusion']} s{r['severity']}", "segment": r.get("segment"),
             "QA category": r["qa_category"], "question": _cell(r["question"]), "reference": _cell(r["reference"]),
             "clean answer": _cell(c["answer"]), "perturbed answer": _cell(r["answer"]),
             f"{field} clean -> perturbed": f"{scale * c[field]:.0f} -> {scale * r[field]:.0f}"}
            for c, r in pairs]
    path = out / "worst_answers.md"
    atomic_write_text(path, f"# The {len(rows)} answers an illusion hurt most ({field})\n\n{markdown_table(rows)}\n")
    return path


def write_language_summary(results: list[Path], out: Path) -> Path:
    """language_scores.json: every COCO caption score (METEOR too, which needs Java) of the original and the
    perturbed answers of each model, with the Language score beside its parts; SPICE is not computed (its
    Stanford models cannot be had offline)."""
    from lanevil_train.evaluation.lane_records import read_records
    from lanevil_train.metrics.vqa import language_scores

    groups: dict[tuple, dict] = {}
    for record in (r for path in results for r in read_records(path, keep_lanes=False)):
        kind = "original" if record["severity"] == 0 else "perturbed"
        group = groups.setdefault((record["model"], record["dataset"], kind), {"pred": {}, "refs": {}})
        group["pred"][record["key"]] = record["answer_tokens"]
        group["refs"][record["key"]] = record["reference_tokens"]
    rows = [{"model": m, "dataset": d, "answers_kind": kind, "answers": len(g["pred"]),
             **language_scores(g["pred"], g["refs"], meteor=True, tokenized=True),
             "SPICE": None, "SPICE_note": "not computed: SPICE needs Stanford CoreNLP models that cannot be had "
                                          "offline"}
            for (m, d, kind), g in groups.items()]
    path = out / "language_scores.json"
    atomic_write_text(path, json.dumps(rows, indent=1) + "\n")
    return path


def test_vlm(cfg: DictConfig, vlm, name: str, out: Path) -> float:
    """The VLM on the test clips (task.suite, else task.cases scenes of data=clips' test split, rendered on the
    fly), with the blind baselines task.blind asks for: the tables of task=evaluate in out/."""
    if cfg.task.suite is None:  # not the whole test split: the task.cases scenes of it, rendered on the fly
        cfg = cfg.copy()
        with open_dict(cfg):
            cfg.task.suite = "synthetic"
    dataset, dataset_name = clip_suite(cfg)
    judge = build_judge(cfg, out)
    reader = text_reader(cfg) if "text" in blind_kinds(cfg) else None
    files = [evaluate_into(vlm, dataset, judge, out, {"model": name, "dataset": dataset_name}, cfg.progress),
             *blind_baselines(cfg, vlm, reader, dataset, judge, out, name, dataset_name)]
    value = write_results(files, out, html=False)
    write_gap_intervals(files[0], out)
    write_visual_reliance(files, out)
    if cfg.task.get("html", True) and (out / "report.md").is_file():
        print(f"Report page: {write_vlm_page(out, files)}")
    return value
