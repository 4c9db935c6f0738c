"""Seeds in task=report (and a multirun's report): results files that share a model label on one dataset are that
model's runs with different seeds. Each run keeps its own rows in the usual tables ("<label> (seed s)"), and
seeds.md adds each model's mean ± std over its seeds and each model's gain over the reference model (task.baseline,
else the first model) with its paired-bootstrap interval (report/intervals.py), as tables and a plot.

A run's seed is the `seed` of the config beside its results (a Hydra run's .hydra/config.yaml, a compare run's
config.yaml, up to three folders above the file).
"""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import OmegaConf

from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.report.tables import markdown_table, write_table


def _first_record(path: Path) -> dict:
    with open(path, encoding="utf-8") as handle:
        try:
            return json.loads(handle.readline())
        except ValueError:
            return {}


def run_seed(path: Path) -> int | None:
    """The training seed of the run a results file belongs to, from the config nearest above it (None if none)."""
    for folder in (path.parent, path.parent.parent, path.parent.parent.parent):
        for config in (folder / ".hydra" / "config.yaml", folder / "config.yaml"):
            if config.is_file():
                seed = OmegaConf.select(OmegaConf.load(config), "seed")
                if seed is not None:
                    return int(seed)
    return None


def seed_runs(files: list[Path]) -> dict[tuple[str, str], dict[int, Path]]:
    """{(model label, dataset): {seed: results file}} of the files whose label repeats on a dataset with a distinct
    seed in each run's config; empty when no label does. Repeats without distinct seeds (a sweep over another setting
    of one model) are left out: they are not seeds, and need a task.label each."""
    by_label: dict[tuple[str, str], list[Path]] = {}
    for path in files:
        first = _first_record(path)
        by_label.setdefault((str(first.get("model")), str(first.get("dataset"))), []).append(path)
    out = {}
    for label, paths in by_label.items():
        if len(paths) < 2:
            continue
        seeds = [run_seed(p) for p in paths]
        if None not in seeds and len(set(seeds)) == len(seeds):
            out[label] = dict(zip(seeds, paths))
    return out


def relabels(groups: dict[tuple[str, str], dict[int, Path]]) -> dict[Path, str]:
    """Each seed run's label in the ordinary tables: "<label> (seed s)"."""
    return {path: f"{label} (seed {seed})" for (label, _), runs in groups.items() for seed, path in runs.items()}


def write_seed_report(files: list[Path], out_dir: Path, baseline: str | None = None, replicates: int = 1000,
                      confidence: float = 0.95, seed: int = 0) -> Path | None:
    """seeds.{md,json,csv} and seed_gains.{json,csv,md} (+ seed_gains[_<dataset>].png) in out_dir when some model has
    several seeds on a dataset; the report's path, or None. Per dataset: models with one run take part as one seed,
    and every run must be scored on the same items."""
    from lanevil_train.evaluation.lane_records import read_records
    from lanevil_train.report.defenses import gain_plot
    from lanevil_train.report.intervals import SeedRuns, gain_rows, gain_text, mean_std_text, seed_rows

    groups = seed_runs(files)
    if not groups:
        return None
    datasets: dict[str, dict[str, dict[int, list[dict]]]] = {}
    for path in files:
        first = _first_record(path)
        label = (str(first.get("model")), str(first.get("dataset")))
        seed_of = {p: s for s, p in groups.get(label, {}).items()}
        datasets.setdefault(label[1], {}).setdefault(label[0], {})[seed_of.get(path, 0)] = \
            read_records(path, keep_lanes=False)
    all_scores, all_gains = [], []
    parts = ["# Seeds", "",
             "Models with several runs are summarised over their seeds: mean ± sample std per category, on average "
             "and on the clean originals; gains over the reference model with a paired bootstrap interval over the "
             f"test cases and the seeds ({replicates} replicates, {confidence:.0%}); * marks a gain whose interval "
             "excludes zero.", ""]
    for dataset, runs in datasets.items():
        if baseline is not None and baseline not in runs:
            raise ValueError(f"task.baseline={baseline!r} is not among the models scored on {dataset}: {list(runs)}")
        reference = baseline or next(iter(runs))
        seeded = SeedRuns(runs)
        names = [s.name for s in seeded.scores]
        scores = [{"dataset": dataset, **row} for row in seed_rows(seeded)]
        all_scores += scores
        parts += [f"## {dataset}: " + ", ".join(f"{n} ({len(s)} seed{'s' if len(s) > 1 else ''})"
                                                 for n, s in runs.items()), ""]
        for score in names:
            table = [{"model": name, **{r["category"]: mean_std_text(r, score) for r in scores if r["name"] == name}}
                     for name in runs]
            parts += [f"### {score}", "", markdown_table(table), ""]
        if len(runs) < 2:
            continue
        gains = [{"dataset": dataset, **row}
                 for row in gain_rows(seeded, reference, replicates=replicates, confidence=confidence, seed=seed)]
        all_gains += gains
        for score in names:
            table = [{"model": name, **{r["category"]: gain_text(r, score) for r in gains if r["name"] == name}}
                     for name in runs if name != reference]
            parts += [f"### {score} gain over {reference} (points)", "", markdown_table(table), ""]
        suffix = "" if len(datasets) == 1 else f"_{dataset}"
        plot = gain_plot([{"defense": r["name"], **r} for r in gains], out_dir / f"seed_gains{suffix}.png", names,
                         reference=reference)
        parts += [f"![gains over {reference}]({plot.name})", ""]
    write_table(all_scores, out_dir, "seeds")
    if all_gains:
        write_table(all_gains, out_dir, "seed_gains")
    path = out_dir / "seeds.md"
    atomic_write_text(path, "\n".join(parts))
    return path
