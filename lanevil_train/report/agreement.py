"""Open- vs closed-loop agreement: does the detector that loses least on the open-loop illusion suites also resist the
illusions best when it steers the car? Sato et al. (2021) found that it need not.

Inputs: the evaluate runs' per-image records (report/records.py) and the closed-loop runs' records (runs.jsonl of
task=closed_loop: model, case_id, seed, illusion, severity, perturbed, success and, when the run scores have it,
tlc_min_s), of the same models.

Measures, per model and illusion, each pooled over the severities its side drove or scored:
- open-loop drop: Original - Perturbed of Accuracy and of F1 (the Gap of report/records.py negated: larger = hurt
  more);
- closed-loop ASR (%): the share of the perturbed runs that are attack successes (`success`);
- closed-loop min TLC (s): the mean over the perturbed runs of each run's minimum time to line crossing over the
  attack window (`tlc_min_s` of closed_loop/time_scores.py, capped there; smaller = nearer leaving the lane), when
  the runs carry it.

Rank correlations (Spearman's rho and Kendall's tau-b, scipy.stats; tied values share their mean rank) of an open-loop
drop with a closed-loop measure, over points:
- per illusion: one point per model (a rank correlation needs at least MIN_POINTS of them);
- all, unit "models": one point per model, its measures pooled over every illusion both sides share;
- all, unit "model x illusion": one point per (model, illusion) pair.
The two loops agree when rho and tau are > 0 against ASR (hurt more open-loop, attacked more successfully) and < 0
against min TLC. With few models a rank correlation takes few values (3 models: rho in {-1, -0.5, 0.5, 1}).

Intervals: percentile bootstrap over cases. A replicate draws the cases with replacement, recomputes every model's
measures from the drawn cases (a case counted as often as drawn) and then the correlations. When both sides drove the
same simulated scenes (the synthetic suite's case sim-<seed>-f<frame> and the closed loop's case of scene <seed>) one
draw of scenes serves both sides (paired); otherwise each side's cases are drawn on their own. Replicates where a
correlation is undefined (every point tied on one side) are left out and counted.

Models: a closed-loop model is the evaluated model with the same weights hash (an evaluation's <results>.run.json and
a closed-loop run's traces/<label>/model.json both record weights_sha256), else the one with the same label when
either side records no hash; the same label with different hashes is no match. Models left unmatched are named in the
notes.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from lanevil_train.files.atomic import atomic_write_text  # noqa: E402
from lanevil_train.report.intervals import CONFIDENCE, REPLICATES, case_key  # noqa: E402
from lanevil_train.report.plots import save_figure  # noqa: E402
from lanevil_train.report.records import RecordSet, ordered, ratio  # noqa: E402
from lanevil_train.report.tables import markdown_table, write_table  # noqa: E402
from lanevil_train.results_log import ResultsLog  # noqa: E402
from lanevil_train.taxonomy import ILLUSION_NAMES  # noqa: E402

CLOSED_LOOP_RUNS = "runs.jsonl"  # tasks/closed_loop.RUNS (not imported: that module loads torch and the simulator)
RUN_FIELDS = ("model", "case_id", "illusion", "perturbed", "success")  # what a closed-loop run record must hold
OPEN_SCORES = ("Accuracy", "F1")
ASR = "ASR"
MIN_TLC = "min TLC"
TLC_FIELD = "tlc_min_s"
AGREES_IF = {ASR: "> 0", MIN_TLC: "< 0"}
POINT_COLUMNS = {ASR: "ASR (%)", MIN_TLC: "min TLC (s)"}
MIN_POINTS = 3
ALL = "all"
BY_MODEL = "models"
BY_PAIR = "model x illusion"
NAME = "agreement"
_SIM_CASE = re.compile(r"sim-(\d+)-f\d+")  # data/illusion_set.synthetic_cases: scene seed, frame

Measure = Callable[[np.ndarray], np.ndarray]  # case weights (R, n_cases) -> the measure under each row (R,)


# ----------------------------------------------------------------------------------------------- rank correlations
def spearman(x, y) -> np.ndarray:
    """Spearman's rho of x and y along their last axis (a row of points per replicate): Pearson's r of their ranks,
    tied values at their mean rank; NaN where a row is constant or holds a NaN."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", stats.ConstantInputWarning)
        ranks = stats.rankdata(np.asarray(x, float), axis=-1), stats.rankdata(np.asarray(y, float), axis=-1)
        return np.asarray(stats.pearsonr(*ranks, axis=-1).statistic)


def kendall(x, y) -> np.ndarray:
    """Kendall's tau-b of x and y along their last axis (tau-b: corrected for ties); NaN as for spearman."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", stats.ConstantInputWarning)
        return np.asarray(stats.kendalltau(np.asarray(x, float), np.asarray(y, float), axis=-1).statistic)


CORRELATIONS = {"spearman": spearman, "kendall": kendall}


def percentile_interval(replicates: np.ndarray, confidence: float) -> tuple[float | None, float | None, int]:
    """(low, high) percentile interval of the finite replicates and how many were undefined (NaN); (None, None) when
    none is finite."""
    finite = replicates[np.isfinite(replicates)]
    undefined = len(replicates) - len(finite)
    if not len(finite):
        return None, None, undefined
    alpha = (1 - confidence) / 2
    low, high = np.quantile(finite, [alpha, 1 - alpha])
    return float(low), float(high), undefined


# ------------------------------------------------------------------------------------------------------ case draws
def scene_seed(case_id: str) -> int | None:
    """The scene seed of a synthetic suite's case ("sim-0000012-f0" -> 12); None for any other case."""
    match = _SIM_CASE.fullmatch(str(case_id))
    return int(match.group(1)) if match else None


@dataclass(frozen=True)
class Cases:
    """What a bootstrap replicate draws: each side's case of a record (`open_case`, `closed_case`), the column of each
    case, and whether both sides share one draw (the same scenes: paired)."""

    open_case: Callable[[dict], object]
    closed_case: Callable[[dict], object]
    open_columns: dict
    closed_columns: dict
    paired: bool

    def weights(self, replicates: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(open, closed) case weights (replicates + 1, n_cases): row 0 all ones (the point estimate), then each
        replicate's draw counts (seeded: the same seed, the same draws)."""
        rng = np.random.default_rng(seed)

        def draw(n: int) -> np.ndarray:
            return np.vstack([np.ones((1, n)), rng.multinomial(n, np.full(n, 1.0 / n), size=replicates)])

        open_weights = draw(len(self.open_columns))
        return open_weights, open_weights if self.paired else draw(len(self.closed_columns))

    def describe(self) -> str:
        if self.paired:
            return (f"paired: both sides drove the same simulated scenes, one draw of the {len(self.open_columns)} "
                    f"scenes serves both")
        return (f"independent: the sides' cases differ, each replicate draws the {len(self.open_columns)} open-loop "
                f"and the {len(self.closed_columns)} closed-loop cases on their own")


def cases_of(open_records: Sequence[dict], closed_records: Sequence[dict]) -> Cases:
    """Paired cases (scene seeds) when every open-loop record is a synthetic case, every closed-loop run has a seed
    and the two share some scene; else each side's own cases: (dataset, case_id) open-loop, case_id closed-loop."""
    seeds = {scene_seed(r["case_id"]) for r in open_records}
    closed_seeds = {r.get("seed") for r in closed_records}
    if None not in seeds and None not in closed_seeds and seeds & closed_seeds:
        columns = {s: i for i, s in enumerate(sorted(seeds | closed_seeds))}
        return Cases(lambda r: scene_seed(r["case_id"]), lambda r: r["seed"], columns, columns, True)
    open_columns = {k: i for i, k in enumerate(sorted({case_key(r) for r in open_records}, key=str))}
    closed_columns = {k: i for i, k in enumerate(sorted({r["case_id"] for r in closed_records}, key=str))}
    return Cases(case_key, lambda r: r["case_id"], open_columns, closed_columns, False)


def case_measure(records: Sequence[dict], parts: Callable[[dict], tuple], combine: Callable[[np.ndarray], np.ndarray],
                 column: Callable[[dict], int], n_cases: int) -> Measure:
    """A measure of `records` as per-case sums of their addends (`parts`), combined under case weights: a case drawn
    twice counts its records twice. NaN under every weight for no records."""
    if not records:
        return lambda weights: np.full(len(weights), np.nan)
    table = np.zeros((n_cases, len(parts(records[0]))))
    for record in records:
        table[column(record)] += parts(record)
    return lambda weights: combine(weights @ table)


def _success_parts(record: dict) -> tuple[float, float]:
    return float(bool(record["success"])), 1.0


def _tlc_parts(record: dict) -> tuple[float, float]:
    return float(record[TLC_FIELD]), 1.0


def has_tlc(record: dict) -> bool:
    """Whether a closed-loop run carries a finite minimum time to line crossing."""
    value = record.get(TLC_FIELD)
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


# ------------------------------------------------------------------------------------------------------ the result
@dataclass
class Agreement:
    """The correlation rows (one per group, unit, open-loop score and closed-loop measure), the points they are
    computed from (model x illusion and each model's `all`), the models' closed-loop labels, how cases were drawn and
    the notes."""

    rows: list[dict] = field(default_factory=list)
    points: list[dict] = field(default_factory=list)
    closed_labels: dict[str, str] = field(default_factory=dict)
    cases: str = ""
    notes: list[str] = field(default_factory=list)


def _common_illusions(rs: RecordSet, closed: dict[str, list[dict]], models: list[str], notes: list[str]) -> list[str]:
    """The illusions every model has perturbed records and perturbed closed-loop runs of, in the paper's order; the
    others named in `notes`."""
    shared, seen = None, set()
    for model in models:
        scored = {r["illusion"] for r in rs.by_model[model].pert}
        driven = {r["illusion"] for r in closed[model] if r["perturbed"]}
        seen |= scored | driven
        shared = scored & driven if shared is None else shared & scored & driven
    illusions = ordered(shared or (), ILLUSION_NAMES)
    if seen - set(illusions):
        notes.append(f"illusions left out (not scored open-loop and driven closed-loop for every model): "
                     f"{', '.join(ordered(seen - set(illusions), ILLUSION_NAMES))}")
    return illusions


def _groups(rs: RecordSet, closed: dict[str, list[dict]], models: list[str], illusions: list[str]) -> dict:
    """{(model, illusion or ALL): (perturbed records, their originals, perturbed closed-loop runs)}: ALL pools the
    illusions."""
    groups = {}
    for model in models:
        index = rs.by_model[model]
        for group in [*illusions, ALL]:
            wanted = illusions if group == ALL else [group]
            pert = [r for r in index.pert if r["illusion"] in wanted]
            runs = [r for r in closed[model] if r["perturbed"] and r["illusion"] in wanted]
            groups[model, group] = (pert, index.originals(pert), runs)
    return groups


def _values(groups: dict, scores: list, closed_names: list[str], cases: Cases, replicates: int, seed: int) -> dict:
    """{(model, group, measure name): its values (replicates + 1,)}, row 0 the point estimate, the others under each
    replicate's draw of cases."""
    open_weights, closed_weights = cases.weights(replicates, seed)
    n_open, n_closed = len(cases.open_columns), len(cases.closed_columns)

    def open_column(record: dict) -> int:
        return cases.open_columns[cases.open_case(record)]

    def closed_column(record: dict) -> int:
        return cases.closed_columns[cases.closed_case(record)]

    values = {}
    for (model, group), (pert, orig, runs) in groups.items():
        for score in scores:
            parts, combine = score.aggregate.additive.parts, score.aggregate.additive.combine
            perturbed, original = (case_measure(part, parts, combine, open_column, n_open) for part in (pert, orig))
            values[model, group, score.name] = original(open_weights) - perturbed(open_weights)
        values[model, group, ASR] = case_measure(runs, _success_parts, ratio(100.0), closed_column,
                                                 n_closed)(closed_weights)
        if MIN_TLC in closed_names:
            values[model, group, MIN_TLC] = case_measure([r for r in runs if has_tlc(r)], _tlc_parts, ratio(1.0),
                                                         closed_column, n_closed)(closed_weights)
    return values


def _undefined(x: np.ndarray, y: np.ndarray, unit: str, open_name: str, closed_name: str) -> str:
    """Why the point estimate of a correlation over the points (x, y) is undefined; "" when it is defined."""
    if len(x) < MIN_POINTS:
        return f"{len(x)} point(s) ({unit}): a rank correlation needs at least {MIN_POINTS}"
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        return f"some point has no {open_name} drop or closed-loop {closed_name}"
    for values, name in ((x, f"{open_name} drop"), (y, f"closed-loop {closed_name}")):
        if np.ptp(values) == 0:
            return f"every point has the same {name}: no ranking"
    return ""


def correlation_row(group: str, unit: str, open_name: str, closed_name: str, x: np.ndarray, y: np.ndarray,
                    confidence: float) -> dict:
    """One table row: the correlations of x and y (replicates + 1, points) -- row 0 the point estimate, the others
    bootstrap replicates -- with their percentile intervals; None (and a note) where undefined."""
    row = {"illusion": group, "unit": unit, "points": int(x.shape[-1]), "open-loop": f"{open_name} drop",
           "closed-loop": closed_name, "agrees if": AGREES_IF[closed_name]}
    note = _undefined(x[0], y[0], unit, open_name, closed_name)
    undefined = None
    for name, correlate in CORRELATIONS.items():
        if note:
            row.update({name: None, f"{name}_low": None, f"{name}_high": None})
            continue
        values = correlate(x, y)
        low, high, undefined = percentile_interval(values[1:], confidence)
        row.update({name: float(values[0]), f"{name}_low": low, f"{name}_high": high})
    row["undefined replicates"] = undefined
    row["note"] = note
    return row


def agreement(rs: RecordSet, closed: dict[str, list[dict]], replicates: int = REPLICATES,
              confidence: float = CONFIDENCE, seed: int = 0, closed_labels: dict[str, str] | None = None) -> Agreement:
    """The agreement of open-loop records `rs` and closed-loop runs `closed` ({evaluated model label: its run
    records}) of the models both have (module docstring); `closed_labels`: a model's closed-loop label where it
    differs."""
    if isinstance(replicates, bool) or not isinstance(replicates, int) or replicates < 1:
        raise ValueError(f"replicates: expected a positive integer number of bootstrap replicates, got {replicates!r}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence: expected a level in (0, 1), e.g. 0.95, got {confidence!r}")
    result = Agreement(closed_labels=dict(closed_labels or {}))
    models = [m for m in rs.models if m in closed and rs.by_model[m].pert]
    if not models:
        result.notes.append("no model has both perturbed evaluate records and closed-loop runs: nothing to correlate")
        return result
    illusions = _common_illusions(rs, closed, models, result.notes)
    if not illusions:
        result.notes.append("no illusion was both scored open-loop and driven closed-loop by every model")
        return result
    groups = _groups(rs, closed, models, illusions)
    scores = [s for s in rs.scores if s.name in OPEN_SCORES and getattr(s.aggregate, "additive", None)]
    if not scores:
        result.notes.append(f"the evaluate records carry none of {', '.join(OPEN_SCORES)}: no open-loop drop")
    runs = [r for (_, group), (_, _, mine) in groups.items() if group == ALL for r in mine]
    closed_names = [ASR, MIN_TLC] if any(has_tlc(r) for r in runs) else [ASR]
    if MIN_TLC not in closed_names:
        result.notes.append(f"the closed-loop runs carry no {TLC_FIELD} (minimum time to line crossing): min TLC "
                            f"left out")
    cases = cases_of([r for (_, group), (pert, orig, _) in groups.items() if group == ALL for r in pert + orig], runs)
    result.cases = cases.describe()
    values = _values(groups, scores, closed_names, cases, replicates, seed)
    names = {**{s.name: f"{s.name} drop" for s in scores}, **{name: POINT_COLUMNS[name] for name in closed_names}}
    for (model, group), (pert, _, mine) in groups.items():
        result.points.append({"model": model, "closed-loop model": result.closed_labels.get(model, model),
                              "illusion": group, "perturbed images": len(pert), "perturbed runs": len(mine),
                              **{column: _number(values[model, group, name][0]) for name, column in names.items()}})
    result.rows = _correlation_rows(values, models, illusions, [s.name for s in scores], closed_names, confidence)
    if len(models) < MIN_POINTS:
        result.notes.append(f"{len(models)} model(s) in both kinds of runs: per-model correlations need at least "
                            f"{MIN_POINTS} (add evaluate and closed-loop runs of more models)")
    return result


def _correlation_rows(values: dict, models: list[str], illusions: list[str], open_names: list[str],
                      closed_names: list[str], confidence: float) -> list[dict]:
    """The table's rows: per illusion over the models, then all over the models and over the (model, illusion)
    pairs; each open-loop drop against each closed-loop measure."""
    units = [(group, BY_MODEL, [(m, group) for m in models]) for group in illusions]
    units += [(ALL, BY_MODEL, [(m, ALL) for m in models]), (ALL, BY_PAIR, [(m, i) for m in models for i in illusions])]
    rows = []
    for group, unit, keys in units:
        for open_name in open_names:
            x = np.stack([values[m, g, open_name] for m, g in keys], axis=-1)
            for closed_name in closed_names:
                y = np.stack([values[m, g, closed_name] for m, g in keys], axis=-1)
                rows.append(correlation_row(group, unit, open_name, closed_name, x, y, confidence))
    return rows


def _number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


# ------------------------------------------------------------------------------------------ reading and matching
@dataclass
class ClosedLoopRuns:
    """Closed-loop run records by model label, each label's weights hash (None when not recorded), and notes."""

    records: dict[str, list[dict]] = field(default_factory=dict)
    digests: dict[str, str | None] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def _json_file(path: Path) -> dict:
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return value if isinstance(value, dict) else {}


def read_closed_loop(files: Sequence[Path]) -> ClosedLoopRuns:
    """The closed-loop runs of `files` (runs.jsonl of task=closed_loop): a model's runs from the first file that has
    it (later files' runs of that label named in the notes), its weights hash from traces/<label>/model.json."""
    out = ClosedLoopRuns()
    for path in map(Path, files):
        records = ResultsLog(path).records(drop=("trace",))
        if not records or not all(key in records[0] for key in RUN_FIELDS):
            out.notes.append(f"{path}: not closed-loop runs (no {', '.join(RUN_FIELDS)}): left out")
            continue
        for model in dict.fromkeys(str(r["model"]) for r in records):
            if model in out.records:
                out.notes.append(f"closed-loop model {model!r}: the runs in {path} are left out (its runs of an "
                                 f"earlier folder are used; give each closed-loop run its own label)")
                continue
            out.records[model] = [r for r in records if str(r["model"]) == model]
            out.digests[model] = _json_file(path.parent / "traces" / model / "model.json").get("weights_sha256")
    return out


def open_digests(files: Sequence[Path], records_by_file: dict[Path, list[dict]]) -> dict[str, str | None]:
    """{model label: weights hash} of the evaluate files (their <results>.run.json; None when not recorded or when
    a file holds several models)."""
    out: dict[str, str | None] = {}
    for path in files:
        models = list(dict.fromkeys(str(r["model"]) for r in records_by_file[path]))
        digest = _json_file(path.with_name(f"{path.stem}.run.json")).get("weights_sha256") if len(models) == 1 else None
        for model in models:
            out.setdefault(model, digest)
    return out


def match_models(open_ids: dict[str, str | None], closed_ids: dict[str, str | None]) -> tuple[dict[str, str], list]:
    """({closed-loop label: evaluated label}, notes): the same weights hash, else the same label where either side
    records no hash; an evaluated model takes one closed-loop model at most."""
    matched: dict[str, str] = {}
    notes = []
    for label, digest in closed_ids.items():
        same = [m for m, d in open_ids.items() if digest and d == digest]
        if len(same) > 1:
            same = [m for m in same if m == label] or same
        if len(same) > 1:
            notes.append(f"closed-loop model {label!r}: its weights are those of several evaluated models "
                         f"({', '.join(same)}): not matched")
            continue
        if same:
            target = same[0]
        elif label in open_ids and (digest is None or open_ids[label] is None):
            target = label
        elif label in open_ids:
            notes.append(f"closed-loop model {label!r}: not matched, its weights ({digest[:12]}) are not those of the "
                         f"evaluated {label!r} ({open_ids[label][:12]})")
            continue
        else:
            notes.append(f"closed-loop model {label!r}: no evaluated model of the same weights or label")
            continue
        if target in matched.values():
            notes.append(f"closed-loop model {label!r}: the evaluated {target!r} is already matched: left out")
            continue
        matched[label] = target
    left = [m for m in open_ids if m not in matched.values()]
    if left:
        notes.append(f"evaluated model(s) without closed-loop runs: {', '.join(left)}")
    return matched, notes


# ---------------------------------------------------------------------------------------------------- the output
def scatter(points: Sequence[dict], path: str | Path, open_name: str = "Accuracy", subtitle: str = "") -> Path | None:
    """Open-loop drop vs closed-loop ASR, one point per model x illusion, coloured and labelled by model (`subtitle`
    under the title); None (no file) when no point has both values."""
    drop, shown = f"{open_name} drop", [p for p in points if p["illusion"] != ALL]
    shown = [p for p in shown if p.get(drop) is not None and p.get(POINT_COLUMNS[ASR]) is not None]
    if not shown:
        return None
    fig, ax = plt.subplots(figsize=(5.2, 4.0))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, model in enumerate(dict.fromkeys(p["model"] for p in shown)):
        mine = [p for p in shown if p["model"] == model]
        xs, ys = [p[drop] for p in mine], [p[POINT_COLUMNS[ASR]] for p in mine]
        ax.scatter(xs, ys, color=colors[k % len(colors)], label=model, s=22)
        for x, y in zip(xs, ys):
            ax.annotate(model, (x, y), fontsize=6, xytext=(3, 2), textcoords="offset points")
    ax.set_xlabel(f"open-loop {open_name} drop (Original - Perturbed, points)")
    ax.set_ylabel("closed-loop ASR (%)")
    ax.set_title("Open- vs closed-loop: one point per model x illusion" + (f"\n{subtitle}" if subtitle else ""),
                 fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def _interval_text(row: dict, name: str) -> str:
    if row[name] is None:
        return "–"
    low, high = row[f"{name}_low"], row[f"{name}_high"]
    return f"{row[name]:+.2f} " + ("[n/a]" if low is None else f"[{low:+.2f}, {high:+.2f}]")


def display_rows(rows: Sequence[dict], confidence: float) -> list[dict]:
    """The rows as agreement.md shows them: each correlation with its interval in one cell."""
    keep = ("illusion", "unit", "points", "open-loop", "closed-loop", "agrees if")
    return [{**{k: row[k] for k in keep},
             **{f"{name.capitalize()} [{confidence:.0%} CI]": _interval_text(row, name) for name in CORRELATIONS},
             "note": row["note"]} for row in rows]


def agreement_markdown(result: Agreement, replicates: int, confidence: float, seed: int, plot: Path | None) -> str:
    """agreement.md: what is correlated, the table, the points, the notes and the scatter plot."""
    points = [{k: ("–" if v is None else v) for k, v in p.items()} for p in result.points]
    parts = ["# Open- vs closed-loop agreement", "",
             "Rank correlation (Spearman's rho, Kendall's tau-b) of each model's open-loop drop (Original - "
             "Perturbed, points) with its closed-loop ASR (%) and, when the runs carry it, its mean minimum time to "
             "line crossing (s). Unit `models`: one point per model (per illusion, or `all`: pooled over the "
             "illusions); `model x illusion`: one point per pair. The two loops agree when the correlation is > 0 "
             "with ASR and < 0 with min TLC. With 3 models a rank correlation takes only a few values "
             "(rho in {-1, -0.5, 0.5, 1}).", "",
             f"Intervals: {confidence:.0%} percentile bootstrap over cases, {replicates} replicates, seed {seed}; "
             f"cases {result.cases or 'n/a'}.", "",
             "## Rank correlations", "", markdown_table(display_rows(result.rows, confidence)), "",
             "## Points", "", markdown_table(points, digits=2), ""]
    if result.notes:
        parts += ["## Notes", "", *(f"- {note}" for note in result.notes), ""]
    if plot is not None:
        parts += [f"![Open-loop drop vs closed-loop ASR]({plot.name})", ""]
    return "\n".join(parts)


def write_agreement(result_files: Sequence[Path], closed_files: Sequence[Path], out: str | Path,
                    labels: dict[Path, str] | None = None, replicates: int = REPLICATES,
                    confidence: float = CONFIDENCE, seed: int = 0) -> Path:
    """agreement.{md,json,csv}, agreement_points.{json,csv,md} and agreement.png in `out` from evaluate results files
    and closed-loop runs.jsonl files; `labels`: a model label for the records of some results files (as
    write_results has it). Returns agreement.md's path."""
    from lanevil_train.evaluation.lane_records import read_records
    from lanevil_train.report.specs import record_set

    out, labels = Path(out), labels or {}
    by_file = {}
    for path in result_files:
        records = read_records(path, keep_lanes=False)
        by_file[path] = [{**r, "model": labels[path]} for r in records] if path in labels else records
    closed = read_closed_loop(closed_files)
    matched, notes = match_models(open_digests(result_files, by_file), closed.digests)
    rs = record_set([r for records in by_file.values() for r in records])
    result = agreement(rs, {target: closed.records[label] for label, target in matched.items()}, replicates,
                       confidence, seed, closed_labels={target: label for label, target in matched.items()})
    result.notes = closed.notes + notes + result.notes
    write_table(result.rows, out, NAME)
    write_table(result.points, out, f"{NAME}_points")
    pooled = [r for r in result.rows if (r["illusion"], r["unit"], r["closed-loop"]) == (ALL, BY_PAIR, ASR)
              and r["open-loop"] == f"{OPEN_SCORES[0]} drop"]
    plot = scatter(result.points, out / f"{NAME}.png", OPEN_SCORES[0],
                   f"Spearman {_interval_text(pooled[0], 'spearman')}" if pooled else "")
    path = out / f"{NAME}.md"
    atomic_write_text(path, agreement_markdown(result, replicates, confidence, seed, plot))
    return path
