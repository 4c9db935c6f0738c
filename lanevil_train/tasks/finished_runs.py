"""Finished training runs read back by their records: each run's defense and seed (from its saved config), and the
per-image records of every run under a folder, grouped by defense and seed, for task=compare task.runs=[...]."""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from lanevil_train.evaluation.lane_records import read_records
from lanevil_train.report.defenses import REFERENCE

log = logging.getLogger(__name__)

RESULT_FILES = ("robustness/per_image.jsonl", "per_image.jsonl", "test/per_answer.jsonl", "per_answer.jsonl")


def results_of(run: Path) -> Path | None:
    """A run's suite results: robustness/per_image.jsonl of a detector's train run, test/per_answer.jsonl of a
    VLM's, or the per_image.jsonl / per_answer.jsonl of an evaluate run; None when it has none."""
    return next((run / name for name in RESULT_FILES if (run / name).is_file()), None)


def _run_config(run: Path) -> DictConfig | None:
    """A run's config: its .hydra/config.yaml (a command-line run) or config.yaml (a compare's run), if any."""
    for config in (run / ".hydra" / "config.yaml", run / "config.yaml"):
        if config.is_file():
            return OmegaConf.load(config)
    return None


def _defense_of(run: Path, records: list[dict]) -> str:
    """A run's defense: from its .hydra/config.yaml or config.yaml, else from its label <model>-<bb>[+<defense>]."""
    config = _run_config(run)
    name = OmegaConf.select(config, "defense.name") if config is not None else None
    if name:
        return str(name)
    labels = sorted({r.get("model", "") for r in records})
    if len(labels) != 1:
        raise ValueError(f"task.runs: {run} has no config naming its defense and {len(labels)} model labels {labels}")
    return labels[0].split("+", 1)[1] if "+" in labels[0] else REFERENCE


def _seed_of(run: Path) -> int:
    """A run's training seed, from its config (0 when it has none)."""
    config = _run_config(run)
    seed = OmegaConf.select(config, "seed") if config is not None else None
    return int(seed) if seed is not None else 0


def _run_dirs(path: Path) -> tuple[list[tuple[Path, Path]], list[Path]]:
    """(run directory, results file) for a run, an evaluate output, or a directory of runs one or two levels down
    (a sweep, a compare's runs/<defense>/ or runs/<defense>/seed<s>/); and the subdirectories skipped for having no
    results (a run that failed or is still training)."""
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
            if results is not None:
                found.append((sub, results))
                continue
            seeds = [(d, results_of(d)) for d in sorted(sub.iterdir()) if d.is_dir() and d.name.startswith("seed")]
            found += [(d, r) for d, r in seeds if r is not None]
            skipped += [d for d, r in seeds if r is None] if seeds else [sub]
    if not found:
        raise FileNotFoundError(f"task.runs: no robustness/per_image.jsonl (or a VLM's test/per_answer.jsonl) in "
                                f"{path} or its subdirectories")
    key = lambda t: (0, int(t[0].name), "") if t[0].name.isdigit() else (1, 0, t[0].name)  # noqa: E731
    return sorted(found, key=key), sorted(skipped)


def records_from_runs(runs: list[str]) -> tuple[dict[str, dict[int, list[dict]]], dict[str, dict[int, str]]]:
    """{defense: {seed: records}} and {defense: {seed: run dir}} from run directories trained elsewhere (a defense's
    runs with different `seed` values are its seeds); `none` first.

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
            defense, seed = _defense_of(run, recs), _seed_of(run)
            if seed in records.get(defense, {}):
                raise ValueError(f"task.runs: defense {defense!r} with seed={seed} found twice: "
                                 f"{where[defense][seed]} and {run}")
            records.setdefault(defense, {})[seed] = recs
            where.setdefault(defense, {})[seed] = str(run)
    note = f"; skipped for having no results (no complete robustness/per_image.jsonl): {skipped}" if skipped else ""
    if not any(d != REFERENCE for d in records):
        found_text = (f"only {REFERENCE!r} has results ({', '.join(where[REFERENCE].values())})" if records
                      else "no run has results")
        raise ValueError(f"task.runs={list(runs)}: {found_text}; need the results of {REFERENCE!r} and at least one "
                         f"other defense to compare with it{note}")
    if skipped:
        log.warning("compare: task.runs%s", note)
    order = sorted(records, key=lambda d: d != REFERENCE)
    return ({d: dict(sorted(records[d].items())) for d in order}, {d: dict(sorted(where[d].items())) for d in order})
