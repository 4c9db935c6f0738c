"""task=compare: train the model once per defense, score each on the illusion suite, report each defense's gain
over `none` (paper Fig. enhance). Each run is kept in <out>/runs/<defense>/, so an interrupted compare resumes.

Each run's config is composed as if the user had typed `task=train defense=<d>` with all their other
command-line overrides; task=compare's own suite keys are copied into it.

For a VLM (model=vlm/<backend>, Fig. enhance c-d) every defense that changes weights (none, pgd, mixup, aam, aam++)
fine-tunes the model with the same budget; a textual defense (pat++, pat, self_reminder, and the PAT++ of mida) is
then tuned for the model that the listed defense with the same visual part fine-tuned (`none` for pat++, aam++ for
mida), so its gain is the prompt's own. A textual defense whose visual part no listed defense has (mida without
aam++) fine-tunes in its own run first.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from lanevil_train.data.formats.atomic import atomic_write_text
from lanevil_train.report.defenses import (REFERENCE, best_defense, defense_gain, defense_scores, gain_pivot,
                                           headline_of, write_defense_report)
from lanevil_train.report.specs import spec_for
from lanevil_train.report.tables import print_table
from lanevil_train.tasks.builders import build_defense, build_model, is_vlm, model_config, output_dir
from lanevil_train.tasks.config_check import check_config, interpolated_from, known_defenses
from lanevil_train.tasks.scoring import read_records

log = logging.getLogger(__name__)

DONE = "done.json"  # written beside a run's suite results (robustness/ of a detector, test/ of a VLM) once complete
RESULT_FILES = ("robustness/per_image.jsonl", "per_image.jsonl", "test/per_answer.jsonl", "per_answer.jsonl")
SUITE_KEYS = ("suite", "cases", "illusions", "severities", "repeats", "test_after_fit", "init_from")


def check_defenses(defenses: list[str]) -> list[str]:
    """Validate task.defenses: known names, no repeats, `none` among them, something to compare it with."""
    known = known_defenses()
    defenses = [str(d) for d in defenses]
    bad = [d for d in defenses if d not in known]
    if bad:
        raise ValueError(f"task.defenses: unknown defense(s) {bad}; expected names of defense configs "
                         f"(conf/defense/*.yaml, or a hydra.searchpath folder's defense/): {known}")
    repeated = sorted({d for d in defenses if defenses.count(d) > 1})
    if repeated:
        raise ValueError(f"task.defenses: {repeated} listed more than once")
    if REFERENCE not in defenses:
        raise ValueError(f"task.defenses={defenses} must include {REFERENCE!r}: it is the reference every "
                         f"defense's gain is measured against")
    if len(defenses) < 2:
        raise ValueError(f"task.defenses={defenses}: add at least one defense to compare with {REFERENCE!r}")
    return defenses


def run_overrides(user: list[str]) -> list[str]:
    """The user's command-line overrides that apply to every run: without task/defense/output_dir entries.

    defense.* and ckpt_path are refused: they cannot mean the same thing for every defense.
    """
    keep = []
    for override in user:
        key = override.split("=", 1)[0].lstrip("+~")
        if key in ("task", "defense", "output_dir") or key.startswith("task."):
            continue
        if key.startswith("defense."):
            raise ValueError(f"task=compare: override {override!r} would apply to every defense; put the setting in "
                             f"a defense config (conf/defense/<name>.yaml) and list that name in task.defenses")
        if key == "ckpt_path":
            raise ValueError(f"task=compare: {override!r} is not used; each run resumes from its own "
                             f"runs/<defense>/checkpoints/last.ckpt")
        keep.append(override)
    return keep


def compose_run(cfg: DictConfig, defense: str, overrides: list[str], run_dir: Path,
                source: Path | None = None) -> DictConfig:
    """The config of `task=train defense=<defense>` plus `overrides`, with compare's suite keys and run_dir;
    checked (config_check), so a bad value raises ConfigError naming its key. `source`: a VLM run whose fine-tuned
    model this run's textual defense is tuned for (its visual part is then done)."""
    from hydra import compose

    run_cfg = compose(config_name="config", overrides=[*overrides, "task=train", f"defense={defense}"])
    with open_dict(run_cfg):
        for key in SUITE_KEYS:
            run_cfg.task[key] = OmegaConf.to_container(cfg.task[key]) if OmegaConf.is_config(cfg.task[key]) \
                else cfg.task[key]
        run_cfg.output_dir = str(run_dir)
        last = run_dir / "checkpoints" / "last.ckpt"
        run_cfg.ckpt_path = str(last) if last.is_file() else None
    check_config(run_cfg, where=f"the config of the defense={defense} run")
    if source is not None:
        from lanevil_train.tasks.vlm_train import MODEL_FOLDER, trained_model

        model = trained_model(run_cfg, source / MODEL_FOLDER)
        with open_dict(run_cfg):
            run_cfg.defense.callback, run_cfg.defense.mixer = None, None
            run_cfg.model.path, run_cfg.model.adapter = model["path"], model["adapter"]
            run_cfg.model.merge_adapter = model["adapter"] is not None  # tuned on the merged weights: faster
    return run_cfg


def visual_part(run_cfg: DictConfig) -> str:
    """What a defense does to the frames while a VLM fine-tunes (its callback and mixer), as comparable text."""
    parts = {key: OmegaConf.to_container(run_cfg.defense[key], resolve=True) if run_cfg.defense.get(key) is not None
             else None for key in ("callback", "mixer")}
    return json.dumps(parts, sort_keys=True)


def vlm_sources(configs: dict[str, DictConfig]) -> dict[str, str | None]:
    """For each defense of a VLM compare, the listed defense whose fine-tuned model its textual part is tuned for:
    the first one without a textual part that does the same to the frames; None for a defense that fine-tunes
    itself."""
    from lanevil_train.tasks.vlm_defense import is_prompt_defense

    plain = [d for d, run_cfg in configs.items() if not is_prompt_defense(run_cfg)]
    return {d: (next((p for p in plain if visual_part(configs[p]) == visual_part(run_cfg)), None)
                if is_prompt_defense(run_cfg) else None) for d, run_cfg in configs.items()}


def results_of(run: Path) -> Path | None:
    """A run's suite results: robustness/per_image.jsonl of a detector's train run, test/per_answer.jsonl of a
    VLM's, or the per_image.jsonl / per_answer.jsonl of an evaluate run; None when it has none."""
    return next((run / name for name in RESULT_FILES if (run / name).is_file()), None)


def check_defense_model(run_cfg: DictConfig, built: dict, models: dict | None = None) -> None:
    """A defense callback that names a part of the model (AAM's `layer`) is checked against the run's model
    (built from run_cfg, untrained) before any run trains. `models`: a cache of built models by model config.

    Such a callback has check_model(model) and MODEL_ARGUMENTS, the constructor arguments the check is about;
    the error names their config keys (defense.callback.<arg>) and the key they are interpolated from.
    """
    callback = built.get("callback")
    if not hasattr(callback, "check_model"):
        return
    spec = model_config(run_cfg)
    key = json.dumps(spec, sort_keys=True, default=str)
    models = {} if models is None else models
    if key not in models:
        models[key] = build_model(spec)
    try:
        callback.check_model(models[key])
    except ValueError as error:
        keys = []
        for arg in getattr(callback, "MODEL_ARGUMENTS", ()):
            source = interpolated_from(run_cfg, f"defense.callback.{arg}")
            keys.append(f"{source}={OmegaConf.select(run_cfg, source)!r} (defense.callback.{arg} is ${{{source}}})"
                        if source else f"defense.callback.{arg}")
        where = f"{', '.join(keys)}: " if keys else ""
        raise ValueError(f"task=compare: the defense={run_cfg.defense.name} run cannot use this model: {where}"
                         f"{error}. Nothing was trained") from None


def done_marker(run_dir: Path, vlm: bool) -> Path:
    """Where a compare marks a run finished: beside its suite results."""
    return run_dir / ("test" if vlm else "robustness") / DONE


def run_defense(cfg: DictConfig, defense: str, overrides: list[str], run_dir: Path,
                source: Path | None = None) -> None:
    """Train and score one defense into run_dir, unless a finished result is there (then nothing is done)."""
    from lanevil_train.tasks.train import train

    done = done_marker(run_dir, is_vlm(cfg))
    if done.is_file():
        log.info("compare: defense=%s already done (%s), skipped", defense, done)
        return
    run_cfg = compose_run(cfg, defense, overrides, run_dir, source)
    state = f"resuming from {run_cfg.ckpt_path}" if run_cfg.ckpt_path else "training"
    state += f" (for the model of {source})" if source is not None else ""
    log.info("compare: defense=%s %s in %s", defense, state, run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(run_cfg, run_dir / "config.yaml")
    result = train(run_cfg)
    _finish_wandb()
    if not _is_rank_zero():
        return
    label = read_records(results_of(run_dir), keep_lanes=False)[0]["model"]
    atomic_write_text(done, json.dumps({"defense": defense, "label": label,  # a kill leaves no torn marker
                                        "perturbed_score": result}, indent=2) + "\n")


def _is_rank_zero() -> bool:
    """False in the extra processes of a multi-process (DDP) run: only rank 0 marks runs done and reports."""
    from pytorch_lightning.utilities.rank_zero import rank_zero_only

    return getattr(rank_zero_only, "rank", 0) == 0


def _finish_wandb() -> None:
    """Close a wandb run the finished training left open, so the next defense logs to a run of its own."""
    import sys

    wandb = sys.modules.get("wandb")
    if wandb is not None and getattr(wandb, "run", None) is not None:
        wandb.finish()


def _defense_of(run: Path, records: list[dict]) -> str:
    """A run's defense: from its .hydra/config.yaml or config.yaml, else from its label <model>-<bb>[+<defense>]."""
    for config in (run / ".hydra" / "config.yaml", run / "config.yaml"):
        if config.is_file():
            name = OmegaConf.select(OmegaConf.load(config), "defense.name")
            if name:
                return str(name)
    labels = sorted({r.get("model", "") for r in records})
    if len(labels) != 1:
        raise ValueError(f"task.runs: {run} has no config naming its defense and {len(labels)} model labels {labels}")
    return labels[0].split("+", 1)[1] if "+" in labels[0] else REFERENCE


def _run_dirs(path: Path) -> tuple[list[tuple[Path, Path]], list[Path]]:
    """(run directory, results file) for a run, an evaluate output, or a directory of runs one level down; and
    the subdirectories skipped for having no results (a run that failed or is still training)."""
    if not path.is_dir():
        raise FileNotFoundError(f"task.runs: {path} is not a directory; expected a run directory or a directory "
                                f"of runs")
    own = results_of(path)
    if own is not None:
        return [(path, own)], []
    found, skipped = [], []
    for sub in path.iterdir():
        if sub.is_dir():
            results = results_of(sub)
            if results is None:
                skipped.append(sub)
            else:
                found.append((sub, results))
    if not found:
        raise FileNotFoundError(f"task.runs: no robustness/per_image.jsonl (or a VLM's test/per_answer.jsonl) in "
                                f"{path} or its subdirectories")
    key = lambda t: (0, int(t[0].name), "") if t[0].name.isdigit() else (1, 0, t[0].name)  # noqa: E731
    return sorted(found, key=key), sorted(skipped)


def records_from_runs(runs: list[str]) -> tuple[dict[str, list[dict]], dict[str, str]]:
    """{defense: records} and {defense: run dir} from run directories trained elsewhere; `none` first.

    Subdirectories without results (or with an empty results file) are skipped and named in the log; at least
    one defense besides `none` must have results, or there is nothing to compare.
    """
    records, where, skipped = {}, {}, []
    for path in map(Path, runs):
        found, empty_dirs = _run_dirs(path)
        skipped += [str(sub) for sub in empty_dirs]
        for run, results in found:
            recs = read_records(results, keep_lanes=False)
            if not recs:
                skipped.append(str(run))
                continue
            defense = _defense_of(run, recs)
            if defense in records:
                raise ValueError(f"task.runs: defense {defense!r} found twice: {where[defense]} and {run}")
            records[defense], where[defense] = recs, str(run)
    note = f"; skipped for having no results (no complete robustness/per_image.jsonl): {skipped}" if skipped else ""
    if not any(d != REFERENCE for d in records):
        found_text = f"only {REFERENCE!r} has results ({where[REFERENCE]})" if records else "no run has results"
        raise ValueError(f"task.runs={list(runs)}: {found_text}; need the results of {REFERENCE!r} and at least one "
                         f"other defense to compare with it{note}")
    if skipped:
        log.warning("compare: task.runs%s", note)
    order = sorted(records, key=lambda d: d != REFERENCE)
    return {d: records[d] for d in order}, {d: where[d] for d in order}


def compare(cfg: DictConfig, overrides: list[str] | None = None) -> float | None:
    """Run (or, with task.runs, only report) the defense comparison; returns the best average perturbed Accuracy
    (None in the non-zero ranks of a DDP run, which only train).

    `overrides`: the command-line overrides every run gets (default: this Hydra run's own, minus task/defense).
    """
    out = Path(cfg.task.out_dir) if cfg.task.get("out_dir") else output_dir(cfg)
    if cfg.task.get("runs"):
        records, runs = records_from_runs(list(cfg.task.runs))
    else:
        defenses = check_defenses(list(cfg.task.defenses))
        if overrides is None:
            from hydra.core.hydra_config import HydraConfig

            searchpath = [o for o in HydraConfig.get().overrides.hydra if o.startswith("hydra.searchpath")]
            overrides = [*searchpath, *HydraConfig.get().overrides.task]  # the user's own configs found too
        common = run_overrides(overrides)
        runs = {d: str(out / "runs" / d) for d in defenses}
        # every run's config and defense arguments are checked before the first one trains
        configs = {d: compose_run(cfg, d, common, Path(runs[d])) for d in defenses}
        if is_vlm(cfg):
            from lanevil_train.tasks.vlm_train import check_vlm_run

            for defense, run_cfg in configs.items():
                try:
                    check_vlm_run(run_cfg)
                except ValueError as error:
                    raise ValueError(f"task.defenses: the defense={defense} run cannot fine-tune or defend this VLM: "
                                     f"{error}. Nothing was trained") from None
            sources = vlm_sources(configs)
        else:
            models: dict[str, object] = {}
            for run_cfg in configs.values():
                check_defense_model(run_cfg, build_defense(run_cfg), models)
            sources = dict.fromkeys(defenses)
        order = sorted(defenses, key=lambda d: sources[d] is not None)  # the fine-tuned models before their prompts
        for i, defense in enumerate(order, 1):
            log.info("compare: [%d/%d] defense=%s", i, len(order), defense)
            source = sources[defense]
            run_defense(cfg, defense, common, Path(runs[defense]), None if source is None else Path(runs[source]))
        if not _is_rank_zero():
            return None
        records = {d: read_records(results_of(Path(runs[d])), keep_lanes=False) for d in defenses}
    scores = defense_scores(records)  # validates: `none` is there, every defense on the same items
    spec = spec_for(records[REFERENCE])
    gains = defense_gain(scores)
    write_defense_report(scores, gains, out, spec, runs)
    headline = headline_of(scores, spec).name
    print_table(gain_pivot(gains, headline),
                title=f"{headline} gain over {REFERENCE} (points) — {out / 'compare.md'}")
    name, value = best_defense(scores, spec)
    log.info("compare: best average perturbed %s %.2f (defense=%s); report in %s", headline, value, name,
             out / "compare.md")
    return value
