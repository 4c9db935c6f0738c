"""Robustness cards of the tasks' runs (report/card.py): robustness_card.json beside task=evaluate's results, and
task=report's card of each model it reports. The numbers come from the record files; what identifies the model and
the suite comes from the run (the checkpoint scored, the suite's Plan) or, in task=report, from the card an
evaluation left beside its results, else from the run's <results>.run.json and its saved config.

A closed-loop run of the same model (task=closed_loop task.out_dir=<the evaluation's folder>/closed_loop, or its
runs.jsonl in the evaluation's folder) adds its ASR and collisions to the card.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import asdict
from pathlib import Path

from omegaconf import OmegaConf

from lanevil_train.evaluation.lane_records import read_records
from lanevil_train.report.card import CARD_FILE, CARDS_DIR, CardError, build_card, card_name, read_card, write_card
from lanevil_train.report.specs import record_set
from lanevil_train.results_log import ResultsLog

log = logging.getLogger(__name__)

CLOSED_LOOP_RUNS = ("runs.jsonl", "closed_loop/runs.jsonl")  # beside a model's results: its closed-loop runs


def command_line() -> str | None:
    """The command that started this run (python -m lanevil_train and its overrides), when Hydra started it."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    return " ".join(["python -m lanevil_train", *HydraConfig.get().overrides.task])


def file_sha256(path) -> str | None:
    """sha256 of a file's bytes; None for no path or one that is not a readable file (a folder: a VLM's)."""
    if not path:
        return None
    path = Path(str(path))
    if not path.is_file():
        return None
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()


def run_config_near(path: Path, levels: int = 3):
    """The saved config of the run a file belongs to: the nearest .hydra/config.yaml or config.yaml at most
    `levels` folders above it (None if none can be read)."""
    folder = path if path.is_dir() else path.parent
    for _ in range(levels):
        for config in (folder / ".hydra" / "config.yaml", folder / "config.yaml"):
            if config.is_file():
                try:
                    return OmegaConf.load(config)
                except Exception:  # noqa: BLE001 - an unreadable config identifies nothing
                    return None
        folder = folder.parent
    return None


def _select(config, key: str):
    value = OmegaConf.select(config, key) if config is not None else None
    return None if value is None else str(value)


def training_identity(checkpoint) -> dict:
    """training_data and defense of the training run that wrote a checkpoint, from that run's saved config."""
    if not checkpoint or not Path(str(checkpoint)).exists():
        return {}
    config = run_config_near(Path(str(checkpoint)))
    if config is None or _select(config, "task.name") not in (None, "train", "compare"):
        return {}
    return {"training_data": _select(config, "data.name"), "defense": _select(config, "defense.name")}


def detector_identity(cfg, model) -> dict:
    """A detector evaluation's model identity: family and backbone of the network's build config (the
    checkpoint's), the checkpoint (or ONNX file) and its sha256, the training run's data and defense."""
    spec = getattr(model, "build_config", None) or {}
    checkpoint = cfg.task.get("onnx") or cfg.get("ckpt_path")
    return {"kind": "detector", "family": (spec.get("model") or {}).get("name"),
            "backbone": (spec.get("backbone") or {}).get("name"), "checkpoint": checkpoint,
            "checkpoint_sha256": file_sha256(checkpoint), "weights_id": getattr(model, "weights_sha256", None),
            **training_identity(checkpoint)}


def vlm_identity(cfg, vlm) -> dict:
    """A VLM evaluation's model identity: its backend and model name, the model folder or checkpoint, its hash."""
    identity = vlm.identity() if hasattr(vlm, "identity") else {}
    checkpoint = cfg.get("ckpt_path") or identity.get("path")
    defense = OmegaConf.select(cfg, "defense.name")
    return {"kind": "vlm", "family": identity.get("backend"), "backbone": identity.get("name"),
            "checkpoint": checkpoint, "checkpoint_sha256": file_sha256(cfg.get("ckpt_path")),
            "weights_id": identity.get("model_hash"), **training_identity(cfg.get("ckpt_path")),
            **({"defense": str(defense)} if defense else {})}


def suite_plan(dataset) -> dict | None:
    """The Plan (data/illusion_set.py) a detector suite was made with: an on-the-fly suite's, with the first scene
    seed, or a built set's build.json plan; None for a test set of another kind."""
    from lanevil_train.data.illusion_set import Plan, read_build_record

    plan = getattr(dataset, "plan", None)
    if isinstance(plan, Plan):
        seeds = [case.seed for case, _ in getattr(dataset, "items", ())]
        return {**asdict(plan), **({"first_seed": min(seeds)} if seeds else {})}
    if all(hasattr(dataset, name) for name in ("kind", "names", "severities", "size")):  # a clip suite on the fly
        return {"kind": dataset.kind, "illusions": list(dataset.names), "severities": list(dataset.severities),
                "size": list(dataset.size), "per_clip": getattr(dataset, "per_clip", None)}
    root = getattr(dataset, "root", None)
    if root is not None and (Path(root) / "build.json").is_file():
        try:
            return read_build_record(root).get("plan")
        except (OSError, ValueError):
            return None
    return None


def _run_file(results: Path) -> dict:
    """<results stem>.run.json beside a results file: what identified the evaluation that wrote it."""
    path = results.with_name(f"{results.stem}.run.json")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def _closed_loop_records(folder: Path) -> list[dict]:
    for name in CLOSED_LOOP_RUNS:
        path = folder / name
        if path.is_file():
            try:
                return ResultsLog(path).records()
            except (OSError, ValueError) as error:
                log.warning("robustness card: closed-loop runs %s left out (%s)", path, error)
    return []


def _relative(path: Path, out: Path) -> str:
    try:
        return str(path.resolve().relative_to(out.resolve()))
    except ValueError:
        return str(path.resolve())


def write_evaluation_card(results: Path, out: Path, identity: dict, plan: dict | None = None,
                          baseline: str | None = None) -> Path | None:
    """robustness_card.json in `out` for the model whose records `results` holds; None (nothing written) when it
    scored no perturbed record (a clean test set)."""
    rs = record_set(read_records(results, keep_lanes=False))
    model = rs.models[0]
    if not rs.by_model[model].pert:
        return None
    identity = dict(identity)
    if identity.get("weights_id") is None:
        run = _run_file(results)
        identity["weights_id"] = run.get("weights_sha256") or run.get("vlm.model_hash")
    reference = baseline if baseline in rs.by_model else None  # the reference's own card: mCE 100
    card = build_card(rs, model, identity=identity, plan=plan, reference=reference,
                      closed_loop=_closed_loop_records(out),
                      run={"dir": str(out.resolve()), "command": command_line(), "files": [_relative(results, out)]})
    path = write_card(out / CARD_FILE, card)
    print(f"Robustness card: {path}")
    return path


def _file_identity(results: Path, label: str) -> tuple[dict, dict | None]:
    """(identity, plan) of the model of a results file: the card an evaluation left beside it (when it is of the
    same model), else what the run's .run.json and saved config say."""
    sibling = results.parent / CARD_FILE
    if sibling.is_file():
        try:
            card = read_card(sibling)
        except CardError as error:
            log.warning("robustness card: %s not used (%s)", sibling, error)
        else:
            if card["model"]["label"] == label:
                return {k: v for k, v in card["model"].items() if k != "label"}, card["suite"]["plan"]
    run, config = _run_file(results), run_config_near(results)
    checkpoint = _select(config, "task.onnx") or _select(config, "ckpt_path")
    identity = {"family": _select(config, "model.name"), "backbone": _select(config, "backbone.name"),
                "checkpoint": checkpoint, "checkpoint_sha256": file_sha256(checkpoint),
                "weights_id": run.get("weights_sha256") or run.get("vlm.model_hash")}
    if "vlm.backend" in run:
        identity.update(kind="vlm", family=run.get("vlm.backend"), backbone=run.get("vlm.name"))
    if _select(config, "task.name") == "train":  # a training run's own suite: its data is the training data
        identity.update(training_data=_select(config, "data.name"), defense=_select(config, "defense.name"))
    else:
        identity.update(training_identity(checkpoint))
    return identity, None


def write_report_cards(files: list[Path], out: Path, labels: dict[Path, str] | None = None,
                       baseline: str | None = None, replicates: int = 1000, confidence: float = 0.95,
                       seed: int = 0) -> list[Path]:
    """The card of every model of a report that scored perturbed records: robustness_card.json in `out` for a
    report of one model, <out>/robustness_cards/<label>.json for several (task=leaderboard task.cards=<that
    folder> ranks them). `labels`: a seed run's label for the records of some files, as write_results has it."""
    labels = labels or {}
    by_model: dict[str, list[Path]] = {}
    own_label: dict[Path, str] = {}
    records = []
    for path in files:
        part = read_records(path, keep_lanes=False)
        if part:
            own_label[path] = str(part[0]["model"])
        if path in labels:
            part = [{**r, "model": labels[path]} for r in part]
        for model in dict.fromkeys(r["model"] for r in part):
            by_model.setdefault(str(model), []).append(path)
        records += part
    if not records:
        return []
    rs = record_set(records)
    models = [m for m in rs.models if rs.by_model[m].pert]
    written = []
    for model in models:
        source = by_model[model][0]
        identity, plan = _file_identity(source, own_label.get(source, model))
        reference = baseline if baseline in rs.by_model else None  # the reference's own card: mCE 100
        card = build_card(rs, model, identity=identity, plan=plan, reference=reference,
                          closed_loop=[r for path in by_model[model] for r in _closed_loop_records(path.parent)],
                          run={"dir": str(out.resolve()), "command": command_line(),
                               "files": [_relative(p, out) for p in by_model[model]]},
                          replicates=replicates, confidence=confidence, seed=seed)
        path = out / CARD_FILE if len(models) == 1 else out / CARDS_DIR / card_name(model)
        if path in written:  # two labels that differ only in characters a file name leaves out
            path = path.with_name(f"{path.stem}-{len(written) + 1}.json")
        written.append(write_card(path, card))
    if written:
        where = written[0] if len(written) == 1 else out / CARDS_DIR
        print(f"Robustness card{'s' if len(written) > 1 else ''}: {where}")
    return written
