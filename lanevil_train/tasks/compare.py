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

from lanevil_train.evaluation.lane_records import read_records
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.report.defenses import (
    REFERENCE,
    best_defense,
    defense_gain,
    defense_scores,
    gain_pivot,
    headline_of,
    write_defense_report,
)
from lanevil_train.report.specs import spec_for
from lanevil_train.report.tables import print_table
from lanevil_train.tasks.builders import build_defense, build_model, model_config, output_dir
from lanevil_train.tasks.config_check import check_config, interpolated_from, known_defenses
from lanevil_train.tasks.finished_runs import records_from_runs, results_of
from lanevil_train.tasks.kinds import is_vlm, task_function
from lanevil_train.tasks.launch import launch_jobs, uses_job_launcher
from lanevil_train.tasks.vlm.builders import MODEL_FOLDER, check_vlm_run, is_prompt_defense, trained_model

log = logging.getLogger(__name__)

DONE = "done.json"  # written beside a run's suite results (robustness/ of a detector, test/ of a VLM) once complete
SUITE_KEYS = ("suite", "cases", "illusions", "severities", "repeats", "test_after_fit", "init_from", "html")


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
    plain = [d for d, run_cfg in configs.items() if not is_prompt_defense(run_cfg)]
    return {d: (next((p for p in plain if visual_part(configs[p]) == visual_part(run_cfg)), None)
                if is_prompt_defense(run_cfg) else None) for d, run_cfg in configs.items()}


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
    result = task_function(run_cfg)(run_cfg)  # task=train for the model's kind
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


def check_seeds(seeds) -> list[int]:
    """task.seeds: distinct integers >= 0 (empty: one run per defense with the run's `seed`)."""
    seeds = list(seeds or [])
    bad = [s for s in seeds if isinstance(s, bool) or not isinstance(s, int) or s < 0]
    if bad:
        raise ValueError(f"task.seeds: expected a list of integers >= 0 (one training run per seed), got {bad}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"task.seeds={seeds} lists a seed twice")
    return seeds


def run_dirs(out: Path, defenses: list[str], seeds: list[int], default_seed: int) -> dict[str, dict[int, Path]]:
    """Where each (defense, seed) run lives: runs/<defense>/ with one seed (task.seeds empty), else
    runs/<defense>/seed<s>/."""
    if not seeds:
        return {d: {default_seed: out / "runs" / d} for d in defenses}
    return {d: {s: out / "runs" / d / f"seed{s}" for s in seeds} for d in defenses}


def compare(cfg: DictConfig, overrides: list[str] | None = None) -> float | None:
    """Run (or, with task.runs, only report) the defense comparison; returns the best average perturbed Accuracy
    (None in the non-zero ranks of a DDP run, which only train, and in a job that runs one of its runs).

    `overrides`: the command-line overrides every run gets (default: this Hydra run's own, minus task/defense).
    With `hydra/launcher=<a job launcher>` (tasks/launch.py) each run is one job of that launcher, and this process
    waits for them; task.run_only="<defense>@<seed>" runs that one run only (what each job does).
    """
    out = Path(cfg.task.out_dir) if cfg.task.get("out_dir") else output_dir(cfg)
    if cfg.task.get("runs"):
        records, runs = records_from_runs(list(cfg.task.runs))
        return write_compare_report(cfg, records, runs, out)
    defenses = check_defenses(list(cfg.task.defenses))
    seeds = check_seeds(cfg.task.get("seeds"))
    user = overrides
    if overrides is None:
        from hydra.core.hydra_config import HydraConfig

        user = list(HydraConfig.get().overrides.task)
        searchpath = [o for o in HydraConfig.get().overrides.hydra if o.startswith("hydra.searchpath")]
        overrides = [*searchpath, *user]  # the user's own configs found too
    common = run_overrides(overrides)
    paths = run_dirs(out, defenses, seeds, int(cfg.seed))
    with_seed = (lambda s: [*common, f"seed={s}"]) if seeds else (lambda s: common)  # noqa: E731
    only = _run_only(cfg, paths)
    # every run's config and defense arguments are checked before the first one trains
    configs = {d: {s: compose_run(cfg, d, with_seed(s), path) for s, path in by_seed.items()}
               for d, by_seed in paths.items()}
    sources = _sources(cfg, defenses, {d: next(iter(by_seed.values())) for d, by_seed in configs.items()})
    order = sorted(defenses, key=lambda d: sources[d] is not None)  # the fine-tuned models before their prompts
    todo = [(d, s) for d in order for s in paths[d] if only in (None, (d, s))]
    if only is None and _launching():
        failed = launch_runs(user, todo, sources, paths, out, is_vlm(cfg))
    else:
        failed = []
        for i, (defense, seed) in enumerate(todo, 1):
            log.info("compare: [%d/%d] defense=%s%s", i, len(todo), defense, f" seed={seed}" if seeds else "")
            source = sources[defense]
            run_defense(cfg, defense, with_seed(seed), paths[defense][seed],
                        None if source is None else paths[source][seed])
    if only is not None or not _is_rank_zero():
        return None
    finished = {d: {s: path for s, path in by_seed.items() if done_marker(path, is_vlm(cfg)).is_file()}
                for d, by_seed in paths.items()}
    records = {d: {s: read_records(results_of(path), keep_lanes=False) for s, path in by_seed.items()}
               for d, by_seed in finished.items() if by_seed}
    runs = {d: {s: str(path) for s, path in by_seed.items()} for d, by_seed in finished.items() if by_seed}
    if not failed:
        return write_compare_report(cfg, records, runs, out)
    listing = "; ".join(f"{d}@{s}" for d, s in failed)
    if REFERENCE in records and len(records) > 1:
        write_compare_report(cfg, records, runs, out, failed=failed)
        where = f"the report of the finished runs is in {out / 'compare.md'}"
    else:
        where = f"too few finished runs for a report ({REFERENCE!r} and another defense are needed)"
    raise RuntimeError(f"task=compare: {len(failed)} run(s) failed: {listing} (each job's error and log are above); "
                       f"{where}. Rerun the same command (task.out_dir={out}) to run only those again")


def _run_only(cfg: DictConfig, paths: dict[str, dict[int, Path]]) -> tuple[str, int] | None:
    """task.run_only "<defense>@<seed>" as (defense, seed), checked against the compare's runs; None when unset."""
    value = cfg.task.get("run_only")
    if value is None:
        return None
    defense, _, seed = str(value).rpartition("@")
    runs = [f"{d}@{s}" for d, by_seed in paths.items() for s in by_seed]
    if not seed.isdigit() or defense not in paths or int(seed) not in paths[defense]:
        raise ValueError(f"task.run_only={value!r}: expected one of this compare's runs, <defense>@<seed>: {runs}")
    return defense, int(seed)


def _sources(cfg: DictConfig, defenses: list[str], configs: dict[str, DictConfig]) -> dict[str, str | None]:
    """Checks each defense against the model before anything trains; for a VLM, the defense whose fine-tuned model
    each textual defense is tuned for (vlm_sources), else None for every defense."""
    if is_vlm(cfg):
        for defense, run_cfg in configs.items():
            try:
                check_vlm_run(run_cfg)
            except ValueError as error:
                raise ValueError(f"task.defenses: the defense={defense} run cannot fine-tune or defend this VLM: "
                                 f"{error}. Nothing was trained") from None
        return vlm_sources(configs)
    models: dict[str, object] = {}
    for run_cfg in configs.values():
        check_defense_model(run_cfg, build_defense(run_cfg), models)
    return dict.fromkeys(defenses)


def _launching() -> bool:
    """Whether this compare runs each training as a job of the Hydra launcher the user picked (tasks/launch.py)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return False
    return uses_job_launcher()


def launch_runs(user: list[str], todo: list[tuple[str, int]], sources: dict[str, str | None],
                paths: dict[str, dict[int, Path]], out: Path, vlm: bool) -> list[tuple[str, int]]:
    """Each unfinished run of `todo` as one job of the current launcher (task=compare with task.run_only), into
    <out>/jobs/<defense>@<seed>/ (the job's log; the run itself writes runs/...); a textual defense's jobs after the
    jobs of the models they are tuned for. Returns the runs that failed."""
    failed = []
    waves = [[(d, s) for d, s in todo if sources[d] is None], [(d, s) for d, s in todo if sources[d] is not None]]
    for wave in waves:
        pending = [(d, s) for d, s in wave if not done_marker(paths[d][s], vlm).is_file()
                   and (sources[d] is None or (sources[d], s) not in failed)]
        failed += [(d, s) for d, s in wave if sources[d] is not None and (sources[d], s) in failed]
        if not pending:
            continue
        log.info("compare: %d run(s) as jobs (%s already done)", len(pending), len(wave) - len(pending))
        jobs = {f"{d}@{s}": [*user, f"task.out_dir={out.resolve()}", f"task.run_only={d}@{s}"] for d, s in pending}
        for (defense, seed), outcome in zip(pending, launch_jobs(jobs, out / "jobs")):
            if not outcome.ok or not done_marker(paths[defense][seed], vlm).is_file():
                failed.append((defense, seed))
    return failed


def write_compare_report(cfg: DictConfig, records: dict[str, dict[int, list[dict]]], runs: dict[str, dict[int, str]],
                         out: Path, failed: list[tuple[str, int]] | None = None) -> float:
    """The compare report from {defense: {seed: records}}: scores (mean and std over seeds), gains over `none` with
    their bootstrap intervals (report/intervals.py), plot and compare.md; returns the best average perturbed
    headline score."""
    from lanevil_train.report.intervals import SeedRuns, gain_rows

    scores = defense_scores(records)  # validates: `none` is there, every defense on the same items
    spec = spec_for(next(iter(records[REFERENCE].values())))
    replicates, confidence = int(cfg.task.get("bootstrap", 1000)), float(cfg.task.get("confidence", 0.95))
    intervals = gain_rows(SeedRuns(records), REFERENCE, replicates=replicates, confidence=confidence,
                          seed=int(cfg.get("seed", 0)))
    gains = defense_gain(scores, intervals=intervals)
    seeds = sorted({s for by_seed in records.values() for s in by_seed})
    note = (f"Intervals: {confidence:.0%} paired bootstrap ({replicates} replicates) over the suite's "
            f"{len({(r['dataset'], r['case_id']) for r in next(iter(records[REFERENCE].values()))})} test cases"
            + (f" and the {len(seeds)} seeds {seeds}" if len(seeds) > 1 else " (one seed: test-set noise only)")
            + "; * marks a gain whose interval excludes zero (report/intervals.py)."
            + (f" **Not included: runs that failed** ({', '.join(f'{d}@{s}' for d, s in failed)}); rerun the compare "
               f"to finish them." if failed else ""))
    write_defense_report(scores, gains, out, spec, runs, interval_note=note)
    if cfg.task.get("html", True):
        from lanevil_train.report.page import write_compare_page

        files = [path for by_seed in runs.values() for run in by_seed.values()
                 if (path := results_of(Path(run))) is not None]
        log.info("compare: report page %s", write_compare_page(out, scores, gains, spec, runs, note, files))
    headline = headline_of(scores, spec).name
    print_table(gain_pivot(gains, headline, text=True),
                title=f"{headline} gain over {REFERENCE} (points) [{confidence:.0%} interval] — {out / 'compare.md'}")
    name, value = best_defense(scores, spec)
    log.info("compare: best average perturbed %s %.2f (defense=%s); report in %s", headline, value, name,
             out / "compare.md")
    return value
