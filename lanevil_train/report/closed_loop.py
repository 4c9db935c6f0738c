"""Closed-loop tables and plots from run records (one dict per run, closed_loop/ and tasks/closed_loop.py).

A run record holds: model, key, case_id, illusion, category, severity (0: the clean twin), perturbed, repeat,
and the scores of closed_loop.run_scores.run_scores (success, max_deviation_m, first_departure_s,
departures_per_km...). Every table compares each group's perturbed runs with their clean twins (the same cases,
illusions and starts driven without the illusion); ASR intervals are Wilson 95 % intervals over the runs (cases
x repeats). Plots: ASR per category (clean vs perturbed, whiskers: the intervals) and the lateral deviation over
time of each category's worst run beside its clean twin, the illusion region shaded.

Time-resolved columns (closed_loop/time_scores.py): TLC at entry and its minimum over the window (s), recovery
time (s) and the share of the runs that went out that had not recovered (%), the false-lane-lock share of the
window's frames (%) and the longest lock (s): each the mean over the group's perturbed runs that have it, beside
"<column> Δ twin": the mean difference from the clean twins (same case, illusion and repeat) over the pairs where
both have it, with its 95 % interval from a paired bootstrap (each replicate draws the twins with replacement, a
twin together with all its perturbed runs: report/reliance.py's). '—' where no run (or no pair) has the score:
records scored before these columns existed, a twin that never went out (recovery), a VLM policy (lock). The plot
closed_loop_tracking.png shows the worst run's tracked boundaries on the road beside the true lane lines and the
illusion's edges.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lanevil_train.closed_loop.run_scores import ASR_THRESHOLD_M, ASR_WINDOW_S  # noqa: E402
from lanevil_train.closed_loop.time_scores import LOCK_EDGE_M, LOCK_TRUE_M, TLC_CAP_S  # noqa: E402
from lanevil_train.files.atomic import atomic_write_text  # noqa: E402
from lanevil_train.report.intervals import CONFIDENCE, REPLICATES  # noqa: E402
from lanevil_train.report.plots import save_figure  # noqa: E402
from lanevil_train.report.records import ordered  # noqa: E402
from lanevil_train.report.reliance import _difference_interval, _scene_weights  # noqa: E402
from lanevil_train.report.tables import markdown_table, write_table  # noqa: E402
from lanevil_train.stats import wilson_interval  # noqa: E402
from lanevil_train.taxonomy import CATEGORIES, ILLUSION_NAMES  # noqa: E402

ALL = "all"
MISSING = "—"


def _not_recovered(record: dict) -> bool | None:
    recovered = record.get("recovered")
    return None if recovered is None else not recovered


# the time-resolved columns: (column, the record's score or a function of the record, scale, digits)
TIME_COLUMNS = (("TLC at entry (s)", "tlc_entry_s", 1.0, 2), ("min TLC (s)", "tlc_min_s", 1.0, 2),
                ("recovery (s)", "recovery_s", 1.0, 2), ("not recovered (%)", _not_recovered, 100.0, 1),
                ("lane lock (%)", "lock_share", 100.0, 1), ("longest lock (s)", "lock_longest_s", 1.0, 2))


def _asr(records: Sequence[dict], key: str = "success") -> tuple[float, float, float]:
    """ASR (%) by the rule `key` (success: from the lane centre; twin_success: from the clean twin's path) and its
    Wilson 95 % interval (%)."""
    wins = sum(bool(r.get(key)) for r in records)
    low, high = wilson_interval(wins, len(records))
    return (100.0 * wins / len(records) if records else float("nan")), 100.0 * low, 100.0 * high


def _mean(values) -> float:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else float("nan")


def twin_key(record: dict) -> tuple:
    """What pairs a perturbed run with its clean twin: (case_id, illusion, repeat)."""
    return record["case_id"], record["illusion"], record["repeat"]


def _score(record: dict, score) -> float | None:
    value = score(record) if callable(score) else record.get(score)
    return None if value is None else float(value)


def paired_difference(perturbed: Sequence[dict], reference: Sequence[dict], score, scale: float = 1.0,
                      replicates: int = REPLICATES, seed: int = 0, pair: Callable[[dict], tuple] = twin_key,
                      unit: Callable[[dict], tuple] | None = None) -> tuple[float, float, float] | None:
    """(mean difference perturbed - reference x scale, its 95 % interval) over the pairs of a run and the reference
    run of the same `pair` key (default: its clean twin, twin_key) where both have the score (a record key or a
    function of the record; None: none); a paired bootstrap drawing the `unit`s (default: the pair keys) with
    replacement, each with all its pairs. None without a pair."""
    unit = unit or pair
    references = {pair(r): r for r in reference}
    pairs = [(r, references.get(pair(r))) for r in perturbed]
    pairs = [(_score(r, score), _score(t, score), unit(r)) for r, t in pairs if t is not None]
    pairs = [(a, b, key) for a, b, key in pairs if a is not None and b is not None]
    if not pairs:
        return None
    units = sorted({key for *_, key in pairs}, key=str)
    index = {key: i for i, key in enumerate(units)}
    first, second = np.zeros((len(units), 2)), np.zeros((len(units), 2))
    for a, b, key in pairs:
        first[index[key]] += (a, 1.0)
        second[index[key]] += (b, 1.0)
    weights = _scene_weights(units, replicates, seed)
    low, high = _difference_interval(first, second, weights, CONFIDENCE, scale)
    return scale * (first[:, 0].sum() - second[:, 0].sum()) / len(pairs), low, high


def time_columns(perturbed: Sequence[dict], clean: Sequence[dict]) -> dict:
    """The time-resolved columns of a group (module docstring): each score's mean over the perturbed runs that have
    it and "<column> Δ twin": the paired difference from the twins with its interval; MISSING where undefined."""
    row = {}
    for column, score, scale, digits in TIME_COLUMNS:
        values = [v for v in (_score(r, score) for r in perturbed) if v is not None]
        row[column] = round(scale * float(np.mean(values)), 4) if values else MISSING
        difference = paired_difference(perturbed, clean, score, scale)
        name = column.rsplit(" (", 1)[0]
        row[f"{name} Δ twin"] = MISSING if difference is None else (
            f"{difference[0]:+.{digits}f} [{difference[1]:.{digits}f}, {difference[2]:.{digits}f}]")
    return row


def _group_row(model: str, column: str, value, perturbed: list[dict], clean: list[dict]) -> dict:
    asr, low, high = _asr(perturbed)
    asr0, low0, high0 = _asr(clean)
    departed = [r["first_departure_s"] for r in perturbed if r.get("first_departure_s") is not None]
    twin, twin_low, twin_high = _asr(perturbed, "twin_success")
    hits = [r["time_to_collision_s"] for r in perturbed if r.get("collision")]
    return {
        "model": model, column: value, "runs": len(perturbed),
        "clean ASR (%)": asr0, "clean 95% CI": f"[{low0:.1f}, {high0:.1f}]",
        "ASR (%)": asr, "95% CI": f"[{low:.1f}, {high:.1f}]",
        "ASR vs twin (%)": twin, "twin 95% CI": f"[{twin_low:.1f}, {twin_high:.1f}]",
        "collisions (%)": 100.0 * len(hits) / len(perturbed) if perturbed else float("nan"),
        "time to collision (s)": float(np.median(hits)) if hits else float("nan"),
        "clean max dev (m)": _mean(r["max_deviation_m"] for r in clean),
        "max dev (m)": _mean(r["max_deviation_m"] for r in perturbed),
        "departed (%)": 100.0 * len(departed) / len(perturbed) if perturbed else float("nan"),
        "time to departure (s)": float(np.median(departed)) if departed else float("nan"),
        "departures/km": _mean(r["departures_per_km"] for r in perturbed),
        **time_columns(perturbed, clean),
    }


def _groups(records: Sequence[dict], by: str):
    """(model, value, perturbed runs, their clean twins) for each model and value of `by` (category | illusion |
    severity), then (model, ALL, ...): for severity the twins are every clean twin of the model."""
    order = {"category": tuple(CATEGORIES), "illusion": ILLUSION_NAMES}.get(by, ())
    for model in dict.fromkeys(r["model"] for r in records):  # in the order they drove
        mine = [r for r in records if r["model"] == model]
        clean_all = [r for r in mine if not r["perturbed"]]
        for value in ordered({r[by] for r in mine if r["perturbed"]}, order):
            perturbed = [r for r in mine if r["perturbed"] and r[by] == value]
            yield model, value, perturbed, clean_all if by == "severity" else [r for r in clean_all if r[by] == value]
        yield model, ALL, [r for r in mine if r["perturbed"]], clean_all


def asr_rows(records: Sequence[dict], by: str) -> list[dict]:
    """One row per model and value of `by` (category | illusion | severity), then the model's `all` row: its
    perturbed runs' scores beside their clean twins' (for severity: every clean twin of the model)."""
    return [_group_row(model, by, value, perturbed, clean) for model, value, perturbed, clean in _groups(records, by)]


def compare_rows(records: Sequence[dict]) -> list[dict]:
    """Category x model: perturbed ASR (%) with its interval, and the clean ASR, one column pair per model."""
    rows = []
    by_category = asr_rows(records, "category")
    for category in dict.fromkeys(row["category"] for row in by_category):
        row = {"category": category}
        for item in (r for r in by_category if r["category"] == category):
            row[f"{item['model']} ASR (%)"] = f"{item['ASR (%)']:.1f} {item['95% CI']}"
            row[f"{item['model']} clean (%)"] = f"{item['clean ASR (%)']:.1f}"
        rows.append(row)
    return rows


def asr_plot(records: Sequence[dict], path: str | Path) -> Path:
    """Bars of ASR per category (and all) for each model, clean (hatched) beside perturbed, Wilson whiskers."""
    groups = list(_groups(records, "category"))
    models = list(dict.fromkeys(model for model, *_ in groups))
    categories = list(dict.fromkeys(value for _, value, *_ in groups))
    width = 0.8 / (2 * len(models))
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(categories) * max(1, len(models) / 2), 3.6))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for m, model in enumerate(models):
        for k, (kind, hatch) in enumerate((("clean", "//"), ("illusion", ""))):
            xs, heights, errs = [], [], [[], []]
            for model_, category, perturbed, clean in groups:
                if model_ != model:
                    continue
                asr, low, high = _asr(clean if kind == "clean" else perturbed)
                xs.append(categories.index(category) - 0.4 + width * (2 * m + k + 0.5))
                heights.append(asr)
                errs[0].append(max(asr - low, 0.0))
                errs[1].append(max(high - asr, 0.0))
            ax.bar(xs, heights, width, yerr=errs, capsize=2, color=colors[m % len(colors)],
                   alpha=0.45 if k == 0 else 0.9, hatch=hatch, label=f"{model} {kind}", edgecolor="black",
                   linewidth=0.4)
    ax.set_xticks(range(len(categories)), [c.replace("_", " ") for c in categories], fontsize=8)
    ax.set_ylabel("ASR (%)")
    ax.set_ylim(0, 105)
    ax.set_title(f"Attack success: > {ASR_THRESHOLD_M} m within {ASR_WINDOW_S} s of the illusion (95 % CI)", fontsize=9)
    ax.legend(fontsize=7, ncol=max(1, len(models)))
    return save_figure(fig, path)


def worst_pairs(records: Sequence[dict]) -> list[tuple[dict, dict]]:
    """Per category, the first model's perturbed run with the largest max deviation and its clean twin."""
    if not records:
        return []
    model = records[0]["model"]
    mine = [r for r in records if r["model"] == model]
    clean = {(r["case_id"], r["illusion"], r["repeat"]): r for r in mine if not r["perturbed"]}
    pairs = []
    for category in ordered({r["category"] for r in mine}, tuple(CATEGORIES)):
        runs = [r for r in mine if r["perturbed"] and r["category"] == category]
        runs = [r for r in runs if (r["case_id"], r["illusion"], r["repeat"]) in clean]
        if runs:
            worst = max(runs, key=lambda r: r["max_deviation_m"])
            pairs.append((worst, clean[(worst["case_id"], worst["illusion"], worst["repeat"])]))
    return pairs


def deviation_plot(pairs: Sequence[tuple[dict, dict]], trace_of: Callable[[dict], list[dict]],
                   path: str | Path) -> Path | None:
    """Lateral deviation over time (0 = entering the illusion region) of each pair (worst run, clean twin), a panel
    each; the illusion region shaded (from entering to leaving it), the end of the attack window and the ASR
    threshold marked."""
    if not pairs:
        return None
    fig, axes = plt.subplots(1, len(pairs), figsize=(3.4 * len(pairs), 3.0), squeeze=False, sharey=True)
    for ax, (run, twin) in zip(axes[0], pairs):
        for record, style, label in ((twin, "--", "clean"), (run, "-", f"{run['illusion']} s{run['severity']}")):
            trace = trace_of(record)
            entry = record.get("entry_s") or 0.0
            ax.plot([s["t"] - entry for s in trace], [s["deviation"] for s in trace], style, label=label)
        # the loop ended on the run's own trace and entry: where it left the illusion region
        leave = next((s["t"] for s in trace if s["s"] >= run["region_m"][1]), trace[-1]["t"])
        ax.axvspan(0.0, leave - entry, color="orange", alpha=0.15, label="on the illusion")
        ax.axvline(ASR_WINDOW_S, color="grey", linestyle="-.", linewidth=0.8, label=f"{ASR_WINDOW_S} s window")
        for sign in (-1, 1):
            ax.axhline(sign * ASR_THRESHOLD_M, color="red", linestyle=":", linewidth=0.8)
        ax.set_title(f"{run['category'].replace('_', ' ')} ({run['case_id']})", fontsize=8)
        ax.set_xlabel("time since entering the illusion (s)", fontsize=8)
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("lateral deviation (m, + right)")
    return save_figure(fig, path)


def tracking_plot(run: dict, trace: list[dict], path: str | Path) -> Path | None:
    """The run's tracked lane boundaries (BOUNDARY_AHEAD_M ahead, on the road) over time since entering the
    illusion, beside the true lane lines, the illusion's footprint edges there and the car's own deviation; the
    false-lane-lock frames marked. None (nothing drawn) for a trace without tracked boundaries or a record
    without its image size (scored before closed_loop_tracking.png existed)."""
    if "image_size" not in run or not any(step.get("left_boundary_m") is not None for step in trace):
        return None
    from lanevil_train.closed_loop.episode import case_scene, ego_lane
    from lanevil_train.closed_loop.time_scores import BOUNDARY_AHEAD_M, illusion_edges, tracking_series

    scene = case_scene(run["seed"], tuple(run["image_size"]))[0]
    centre, width = ego_lane(scene)
    series = tracking_series(trace, scene.road, illusion_edges(run["seed"], run["illusion"], tuple(run["image_size"])))
    entry = run.get("entry_s") or 0.0
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.set_ylim(-1.5 * width, 1.5 * width)  # the ego lane and half of each neighbour
    for i, boundary in enumerate(scene.road.boundaries):
        ax.axhline(boundary.d - centre, color="black", linewidth=0.8, label="true lane lines" if i == 0 else None)
    edge_t = [step["t"] - entry for step, item in zip(trace, series) if item for _ in item["edges"]]
    edge_d = [d - centre for item in series if item for d in item["edges"]]
    ax.scatter(edge_t, edge_d, s=4, color="orange", label="illusion edges")
    shown = [(step["t"] - entry, item) for step, item in zip(trace, series) if item]
    for side, color in (("left", "tab:blue"), ("right", "tab:green")):
        ax.plot([t for t, _ in shown], [item[side] - centre for _, item in shown], color=color,
                label=f"tracked {side} ({BOUNDARY_AHEAD_M:g} m ahead)")
    locks = [t for t, item in shown if item["locked"] and 0.0 <= t <= ASR_WINDOW_S + 1e-9]  # what the score counts
    if locks:
        ax.plot(locks, [-1.4 * width] * len(locks), "|", color="red", markersize=10, label="false lane lock")
    ax.plot([step["t"] - entry for step in trace], [step["deviation"] for step in trace], color="grey",
            linewidth=0.8, linestyle="--", label="car (deviation)")
    ax.axvline(0.0, color="grey", linestyle=":", linewidth=0.8)
    ax.axvline(ASR_WINDOW_S, color="grey", linestyle="-.", linewidth=0.8, label=f"{ASR_WINDOW_S} s window")
    ax.set_xlabel("time since entering the illusion (s)", fontsize=8)
    ax.set_ylabel("lateral position (m from the lane centre, + right)", fontsize=8)
    ax.set_title(f"{run['model']}: {run['illusion']} s{run['severity']} ({run['case_id']})", fontsize=9)
    ax.legend(fontsize=6, loc="upper left", ncol=2)
    return save_figure(fig, path)


def _setting(value) -> str:
    """A setting as the report's first line shows it: floats short (45 mph from m/s is 45.00000000000001)."""
    return f"{value:.10g}" if isinstance(value, float) else str(value)


def write_closed_loop_report(records: Sequence[dict], trace_of: Callable[[dict], list[dict]], out: str | Path,
                             settings: dict) -> Path:
    """Tables (asr_by_category/illusion/severity, asr_compare with several models), plots and closed_loop.md."""
    out = Path(out)
    if not records:
        raise ValueError(f"{out}: no finished closed-loop runs to report")
    sections = [f"# Closed loop\n\nSettings: {', '.join(f'{k}={_setting(v)}' for k, v in settings.items())}.\n",
                f"A run is an attack success when the car deviates more than {ASR_THRESHOLD_M} m from its lane's "
                f"centre within {ASR_WINDOW_S} s of entering the illusion region (the paper, after Sato et al. "
                f"2021). Clean: the same starts without the illusion. ASR vs twin: the same rule on the deviation from "
                f"the clean twin's path at the same arc length (the illusion's push without the detector's own "
                f"bias). Collisions: the car's footprint met a standing illusion's (time from the run's start). "
                f"CI: Wilson 95 % over the runs.\n",
                f"Time-resolved columns (docs/closed_loop.md, Time-resolved metrics): TLC, the first-order time to "
                f"line crossing of the car's outer wheel, at entering the illusion and its minimum over the window "
                f"(capped at {TLC_CAP_S:g} s); recovery: from first exceeding {ASR_THRESHOLD_M} m to the first step "
                f"back within it, and the share of the runs that went out and had not come back by the run's end; "
                f"lane lock: the share of the window's frames where a tracked boundary lies within {LOCK_EDGE_M} m "
                f"of the illusion's footprint edge and over {LOCK_TRUE_M} m from every true lane line, and the "
                f"longest lock. Means over the runs that have the score; Δ twin: the mean difference from the clean "
                f"twins with a paired-bootstrap 95 % interval; {MISSING}: no run has it.\n"]
    for by in ("category", "illusion", "severity"):
        rows = asr_rows(records, by)
        write_table(rows, out, f"asr_by_{by}")
        sections.append(f"## By {by}\n\n{markdown_table(rows)}\n")
    if len({r["model"] for r in records}) > 1:
        rows = compare_rows(records)
        write_table(rows, out, "asr_compare")
        sections.append(f"## Models compared\n\n{markdown_table(rows)}\n")
    from lanevil_train.report.closed_loop_groups import group_difference_rows  # it builds on this module

    rows = group_difference_rows(records)
    if rows:
        write_table(rows, out, "group_difference")
        sections.append("## Groups compared (models labelled <group>@<seed>)\n\nEach group against the "
                        f"reference ({rows[0]['vs']}): the mean difference over the pairs of perturbed runs of one "
                        "seed, case, illusion, severity and repeat, with a paired-bootstrap 95 % interval over the "
                        "(seed, case, illusion, repeat) units; the ASR columns: mean ± std over the seeds "
                        f"(report/closed_loop_groups.py).\n\n{markdown_table(rows)}\n")
    asr_plot(records, out / "asr.png")
    sections.append("![ASR per category](asr.png)\n")
    pairs = worst_pairs(records)
    if deviation_plot(pairs, trace_of, out / "deviation.png"):
        sections.append("![Worst run per category beside its clean twin](deviation.png)\n")
    if pairs:
        worst = max(pairs, key=lambda pair: pair[0]["max_deviation_m"])[0]
        if tracking_plot(worst, trace_of(worst), out / "closed_loop_tracking.png"):
            sections.append("![The worst run's tracked lane boundaries, the true lines and the illusion's edges]"
                            "(closed_loop_tracking.png)\n")
    path = out / "closed_loop.md"
    atomic_write_text(path, "\n".join(sections))
    return path
