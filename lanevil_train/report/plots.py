"""Robustness plots from per-item records (report/records.py), on the spec's headline score (Accuracy for lanes):
score vs severity, a model x illusion gap heatmap, and the worst-breaking cases drawn clean | perturbed (GT lanes
green, predictions red). Each takes a list of records (the spec is inferred) or a RecordSet."""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lanevil_train.files.atomic import atomic_write_bytes  # noqa: E402
from lanevil_train.report.records import item_of  # noqa: E402
from lanevil_train.report.specs import record_set  # noqa: E402

_STYLES = ("-", "--", ":", "-.")


def save_figure(fig, path: str | Path) -> Path:
    """Write a figure as PNG, whole or not at all (atomically; parent folders made), and close it."""
    path = Path(path)
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, image.getbuffer())
    return path


def score_vs_severity(records, path: str | Path) -> Path:
    """One panel per model, one line per category: x = severity 0 (same items' Original) .. 5, y = the headline
    score."""
    rs = record_set(records)
    score = rs.headline
    n = max(len(rs.models), 1)
    fig, axes = plt.subplots(1, n, figsize=(4.5 * n, 3.6), squeeze=False)
    for ax, m in zip(axes[0], rs.models):
        index = rs.by_model[m]
        by_severity = rs.groups(m, ("category", "severity"))
        for j, ((cat,), pert) in enumerate(rs.groups(m, ("category",))):
            points = [(sev, score.aggregate(group)) for (c, sev), group in by_severity if c == cat]
            xs, ys = zip((0, score.aggregate(index.originals(pert))), *points)
            ax.plot(xs, ys, _STYLES[j % len(_STYLES)], marker="o", label=cat)
        ax.set_title(m)
        ax.set_xlabel("severity (0 = original)")
        ax.set_ylabel(f"{score.name} ({rs.spec.unit})")
        ax.set_xticks(range(0, 6))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return save_figure(fig, path)


def gap_heatmap(records, path: str | Path) -> Path:
    """Models x illusion types, colour = the headline score's Gap (Perturbed - Original), each cell annotated; red
    is worse than the original whichever way the score points."""
    rs = record_set(records)
    score = rs.headline
    grid = np.full((len(rs.models), len(rs.illusions)), np.nan)
    for i, m in enumerate(rs.models):
        for (ill,), pert in rs.groups(m, ("illusion",)):
            grid[i, rs.illusions.index(ill)] = rs.by_model[m].pog(pert, [score])[f"{score.name}/Gap"]
    lim = float(np.nanmax(np.abs(grid))) if np.isfinite(grid).any() else 1.0
    lim = lim or 1.0
    fig, ax = plt.subplots(figsize=(1.0 + 0.8 * max(len(rs.illusions), 1), 1.2 + 0.5 * max(len(rs.models), 1)))
    cmap = "RdBu" if score.higher_is_better else "RdBu_r"
    im = ax.imshow(np.ma.masked_invalid(grid), cmap=cmap, vmin=-lim, vmax=lim, aspect="auto")
    for i in range(len(rs.models)):
        for j in range(len(rs.illusions)):
            if np.isfinite(grid[i, j]):
                ax.text(j, i, f"{grid[i, j]:.1f}", ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(rs.illusions)), rs.illusions, rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(len(rs.models)), rs.models, fontsize=8)
    fig.colorbar(im, ax=ax, label=f"{score.name} gap ({rs.spec.unit})")
    ax.set_title(f"{score.name} gap per illusion (Perturbed - Original)")
    return save_figure(fig, path)


def _draw(image_path: str, gt, pred) -> np.ndarray:
    img = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"worst_cases: cannot read image {image_path}")
    thick = max(1, round(min(img.shape[:2]) / 150))
    for lanes, colour in ((gt, (0, 255, 0)), (pred, (0, 0, 255))):  # BGR: GT green, prediction red
        for lane in lanes or []:
            pts = np.asarray(lane, dtype=np.float64).reshape(-1, 2)
            pts = pts[(pts[:, 0] >= 0) & np.isfinite(pts).all(axis=1)]
            if len(pts) >= 2:
                cv2.polylines(img, [np.round(pts).astype(np.int32)], False, colour, thick, cv2.LINE_AA)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def worst_case_pairs(records, k: int = 6) -> list[tuple[dict, dict]]:
    """The k (clean, perturbed) record pairs whose headline score drops most, one per (model, dataset, case_id),
    among pairs whose both image files exist; ties broken by key so the choice is deterministic."""
    rs = record_set(records)
    score = rs.headline
    sign = 1.0 if score.higher_is_better else -1.0
    best: dict[tuple, tuple] = {}
    missing = 0
    for m in rs.models:
        index = rs.by_model[m]
        for r in index.pert:
            c = index.clean.get(item_of(r, rs.spec))
            if c is None or not r.get("image") or not c.get("image"):
                continue
            if not (Path(r["image"]).is_file() and Path(c["image"]).is_file()):
                missing += 1
                continue
            key = (r["model"], r["dataset"], r["case_id"])
            drop = sign * (score.aggregate([c]) - score.aggregate([r]))
            cand = (-drop, key, r["illusion"], r["severity"])
            if key not in best or cand < best[key][0]:
                best[key] = (cand, c, r)
    if missing:
        warnings.warn(f"worst_cases: {missing} perturbed record(s) skipped, image file(s) not found")
    chosen = sorted(best.values(), key=lambda t: t[0])[:k]
    return [(c, r) for _, c, r in chosen]


def worst_cases(records, path: str | Path, k: int = 6) -> Path | None:
    """Draw the k cases whose headline score drops most (clean | perturbed, GT green, prediction red); None (no
    file) when no record pair has readable image paths."""
    if k < 1:
        raise ValueError(f"worst_cases: k must be >= 1, got {k}")
    rs = record_set(records)
    score = rs.headline
    pairs = worst_case_pairs(rs, k)
    if not pairs:
        return None
    fig, axes = plt.subplots(len(pairs), 2, figsize=(8, 2.6 * len(pairs)), squeeze=False)
    for (c, r), row in zip(pairs, axes):
        for ax, rec, label in ((row[0], c, "original"), (row[1], r, f"{r['illusion']} s{r['severity']}")):
            ax.imshow(_draw(rec["image"], rec.get("gt_lanes"), rec.get("pred_lanes")))
            value = score.aggregate([rec])
            ax.set_title(f"{rec['model']} {rec['case_id']} {label}: {score.name} {value:.1f}{rs.spec.unit}", fontsize=8)
            ax.axis("off")
    return save_figure(fig, path)
