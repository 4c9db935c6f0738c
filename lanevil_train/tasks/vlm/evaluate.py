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
from lanevil_train.tasks.builders import build_logger, output_dir
from lanevil_train.tasks.vlm.builders import (
    add_defense_to_report,
    build_defended_vlm,
    build_judge,
    clip_suite,
)
from lanevil_train.vlm.base import VLM, BlindVLM
from lanevil_train.vlm.scoring.evaluation import ANSWERS, PER_ANSWER, evaluate_clips


def run_identity(vlm: VLM, judge, label: dict) -> dict:
    """What makes two VLM evaluations the same: the label, the backend's identity, the judge."""
    return {**{k: str(v) for k, v in label.items()}, **{f"vlm.{k}": v for k, v in vlm.identity().items()},
            "judge": getattr(judge, "name", None)}


def evaluate_vlm(cfg: DictConfig) -> float:
    """Evaluate the VLM; returns its headline score (the judge's, else Language) over the perturbed answers."""
    pl.seed_everything(cfg.seed, workers=True)
    dataset, dataset_name = clip_suite(cfg)  # read and checked before the model is loaded
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    vlm = build_defended_vlm(cfg)  # defense=pat++ defense.prefix_path=...: the tuned prefix before every question
    judge = build_judge(cfg, out)
    name = cfg.task.label or vlm.name
    results = evaluate_into(vlm, dataset, judge, out, {"model": name, "dataset": dataset_name}, cfg.progress)
    files = [results]
    if cfg.task.get("blind"):  # the same questions on grey frames, reported beside the model
        blind = BlindVLM(vlm)
        files.append(evaluate_into(blind, dataset, judge, out / "blind",
                                   {"model": f"{name}-blind", "dataset": dataset_name}, cfg.progress))
    value = write_results(files, out, baseline=cfg.task.baseline)
    add_defense_to_report(out, vlm)
    write_language_summary(files, out)
    write_worst_answers(results, out)
    log_results(build_logger(cfg), out)
    return value


def evaluate_into(vlm: VLM, dataset, judge, out: Path, label: dict, progress: str) -> Path:
    """evaluate_clips into `out`, after checking that results already there come from this same evaluation."""
    identity = run_identity(vlm, judge, label)
    for name in (ANSWERS, PER_ANSWER):
        path = out / name
        claim_results(path, identity, resuming=path.is_file() and path.stat().st_size > 0)
    return evaluate_clips(vlm, dataset, out, label, judge=judge, progress=progress)


def _cell(text: str) -> str:
    """Text as one markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|")


def write_worst_answers(results: Path, out: Path, k: int = 12) -> Path | None:
    """worst_answers.md: the k questions whose answer got most worse under an illusion (by the judge's score,
    else by accuracy), each with its reference, the clean clip's answer and the perturbed clip's; None when no
    answer got worse."""
    from lanevil_train.evaluation.scoring import read_records
    from lanevil_train.report.tables import markdown_table

    records = read_records(results, keep_lanes=False)
    field = next((f for f in ("gpt_score", "minilm_score", "correct") if any(r.get(f) is not None for r in records)),
                 None)
    if field is None:
        return None
    clean = {(r["model"], r["dataset"], r["case_id"], r["qa_id"]): r for r in records if r["severity"] == 0}
    drops = []
    for r in records:
        c = clean.get((r["model"], r["dataset"], r["case_id"], r["qa_id"]))
        if r["severity"] > 0 and c is not None and r.get(field) is not None and c.get(field) is not None \
                and r[field] < c[field]:
            drops.append((c[field] - r[field], r["key"], c, r))
    if not drops:
        return None
    scale = 100.0 if field == "correct" else 1.0
    rows = [{"model": r["model"], "illusion": f"{r['illusion']} s{r['severity']}", "segment": r.get("segment"),
             "QA category": r["qa_category"], "question": _cell(r["question"]), "reference": _cell(r["reference"]),
             "clean answer": _cell(c["answer"]), "perturbed answer": _cell(r["answer"]),
             f"{field} clean -> perturbed": f"{scale * c[field]:.0f} -> {scale * r[field]:.0f}"}
            for _, _, c, r in sorted(drops, key=lambda d: (-d[0], d[1]))[:k]]
    path = out / "worst_answers.md"
    atomic_write_text(path, f"# The {len(rows)} answers an illusion hurt most ({field})\n\n{markdown_table(rows)}\n")
    return path


def write_language_summary(results: list[Path], out: Path) -> Path:
    """language_scores.json: every COCO caption score (METEOR too, which needs Java) of the original and the
    perturbed answers of each model, with the Language score beside its parts; SPICE is not computed (its
    Stanford models cannot be had offline)."""
    from lanevil_train.evaluation.scoring import read_records
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
    fly), with its blind baseline when task.blind: the tables of task=evaluate in out/."""
    from lanevil_train.vlm.base import BlindVLM

    if cfg.task.suite is None:  # not the whole test split: the task.cases scenes of it, rendered on the fly
        cfg = cfg.copy()
        with open_dict(cfg):
            cfg.task.suite = "synthetic"
    dataset, dataset_name = clip_suite(cfg)
    judge = build_judge(cfg, out)
    files = [evaluate_into(vlm, dataset, judge, out, {"model": name, "dataset": dataset_name}, cfg.progress)]
    if cfg.task.get("blind"):
        files.append(evaluate_into(BlindVLM(vlm), dataset, judge, out / "blind",
                                   {"model": f"{name}-blind", "dataset": dataset_name}, cfg.progress))
    return write_results(files, out)
