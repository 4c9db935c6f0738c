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
from omegaconf import DictConfig

from lanevil_train.errors import prefixed
from lanevil_train.evaluation.results import log_results, write_results
from lanevil_train.evaluation.streaming import claim_results
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.tasks.builders import build_logger, build_split, instantiate_at, output_dir
from lanevil_train.tasks.vlm_defense import (
    add_defense_to_report,
    check_prompt_defense,
    is_prompt_defense,
    with_prompt_defense,
)
from lanevil_train.vlm.base import VLM, BlindVLM
from lanevil_train.vlm.scoring.evaluation import ANSWERS, PER_ANSWER, evaluate_clips

# Generation and prompt settings of a local backend that a trained model (ckpt_path) is evaluated with.
GENERATION_KEYS = ("name", "max_new_tokens", "batch_size", "frames_as", "system_prompt", "do_sample", "temperature",
                   "seed")


def generation_settings(cfg: DictConfig) -> dict:
    """The model node's generation and prompt settings (for a model trained here, loaded from its checkpoint)."""
    return {key: cfg.model[key] for key in GENERATION_KEYS if key in cfg.model}


def build_vlm(cfg: DictConfig) -> VLM:
    """The VLM backend cfg.model configures (a node with a `_target_`; its training keys left out), or, with
    ckpt_path, the model a task=train run saved in that checkpoint; built now: a bad path fails here."""
    from lanevil_train.tasks.vlm_train import inference_node

    if cfg.ckpt_path is not None:
        from lanevil_train.vlm.training.finetune import load_finetuned

        return load_finetuned(cfg.ckpt_path, "ckpt_path").vlm(**generation_settings(cfg))
    vlm = instantiate_at(inference_node(cfg.model), "model")
    if not isinstance(vlm, VLM):
        raise ValueError(f"model._target_={cfg.model._target_}: built a {type(vlm).__name__}, expected a "
                         f"lanevil_train.vlm.base.VLM")
    return vlm


def build_judge(cfg: DictConfig, out: Path):
    """The judge cfg.judge configures, or None (judge=none); an LLM judge's reply cache defaults to
    out/judge_cache.jsonl."""
    node = cfg.get("judge")
    if node is None or node.get("_target_") is None:
        return None
    extra = {"cache_path": str(out / "judge_cache.jsonl")} if "cache_path" in node and node.cache_path is None else {}
    return instantiate_at(node, "judge", **extra)


def clip_suite(cfg: DictConfig):
    """(dataset, name) of the clips to evaluate on: task.suite=synthetic (task.cases scenes rendered on the fly with
    task.illusions and task.severities; corruptions / combined: the corruption or illusion-pair suite of the
    clips), a folder written by task=build data=clips, a DriveLM-style QA JSON file, or (task.suite=null)
    data=clips' test split."""
    from lanevil_train.vlm.clips.clip_set import ClipSetDataset, SyntheticClipSuite

    suite, task, clips = cfg.task.suite, cfg.task, cfg.data.name == "clips"
    if suite is None:
        if not clips:
            raise ValueError("task.suite: a VLM answers questions about clips: give task.suite=synthetic, a clip "
                             "suite folder (task=build data=clips) or a DriveLM QA JSON file, or use data=clips")
        return build_split(cfg, "test"), "clips-test"
    if suite in ("synthetic", "corruptions", "combined"):
        kind = {"synthetic": "illusions"}.get(suite, suite)
        first_seed = cfg.data.test.first_seed if clips else 1000000
        size = tuple(cfg.data.size) if clips else (360, 640)
        illusions = "all" if task.illusions == "all" else list(task.illusions)
        try:
            dataset = SyntheticClipSuite(task.cases, first_seed, illusions, tuple(task.severities), size, kind=kind)
        except ValueError as error:
            raise prefixed(error, f"task.suite={suite}") from None
        if kind != "illusions":
            return dataset, f"synthetic-clips-{kind}"
        return dataset, "synthetic-clips"
    path = Path(suite)
    try:
        if path.is_file() and path.suffix == ".json":
            return ClipSetDataset.from_drivelm(path), path.stem
        return ClipSetDataset(path), path.name
    except (FileNotFoundError, ValueError) as error:
        raise prefixed(error, f"task.suite={suite}") from None


def run_identity(vlm: VLM, judge, label: dict) -> dict:
    """What makes two VLM evaluations the same: the label, the backend's identity, the judge."""
    return {**{k: str(v) for k, v in label.items()}, **{f"vlm.{k}": v for k, v in vlm.identity().items()},
            "judge": getattr(judge, "name", None)}


def evaluate_vlm(cfg: DictConfig) -> float:
    """Evaluate the VLM; returns its headline score (the judge's, else Language) over the perturbed answers."""
    pl.seed_everything(cfg.seed, workers=True)
    dataset, dataset_name = clip_suite(cfg)  # read and checked before the model is loaded
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    if is_prompt_defense(cfg):
        check_prompt_defense(cfg)
    vlm = build_vlm(cfg)
    if is_prompt_defense(cfg):  # defense=pat++ defense.prefix_path=...: the tuned prefix before every question
        vlm = with_prompt_defense(cfg, vlm)
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
