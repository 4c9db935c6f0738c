"""Robustness plots from per-image records (see report/robustness.py): accuracy vs severity, a model x illusion
gap heatmap, and the worst-breaking cases drawn clean | perturbed (GT lanes green, predictions red)."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lanevil_train.report.robustness import (  # noqa: E402
    CATEGORIES, SEVERITIES, _indexes, _ordered, type_table, validate_records,
)

_STYLES = ("-", "--", ":", "-.")


def save_figure(fig, path: str | Path) -> Path:
    """Write a figure (parent folders made) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def accuracy_vs_severity(records: list[dict], path: str | Path) -> Path:
    """One panel per model, one line per category: x = severity 0 (same cases' Original) .. 5, y = Accuracy %."""
    models, recs, idx = _indexes(records)
    cats = _ordered((r["category"] for r in recs if r["severity"] > 0), CATEGORIES)
    fig, axes = plt.subplots(1, max(len(models), 1), figsize=(4.5 * max(len(models), 1), 3.6), squeeze=False)
    for ax, m in zip(axes[0], models):
        for j, cat in enumerate(cats):
            pert = [r for r in idx[m].pert if r["category"] == cat]
            if not pert:
                continue
            xs, ys = [0], [idx[m].pog(pert)["Accuracy/Original"]]
            for s in SEVERITIES:
                group = [r for r in pert if r["severity"] == s]
                if group:
                    xs.append(s)
                    ys.append(100.0 * float(np.mean([r["accuracy"] for r in group])))
            ax.plot(xs, ys, _STYLES[j % len(_STYLES)], marker="o", label=cat)
        ax.set_title(m)
        ax.set_xlabel("severity (0 = original)")
        ax.set_ylabel("Accuracy (%)")
        ax.set_xticks(range(0, 6))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return save_figure(fig, path)


def gap_heatmap(records: list[dict], path: str | Path) -> Path:
    """Models x illusion types, colour = Accuracy gap (Perturbed - Original, %), each cell annotated."""
    rows = type_table(records)
    models = list(dict.fromkeys(r["model"] for r in rows))
    illusions = _ordered((r["illusion"] for r in rows), [n for names in CATEGORIES.values() for n in names])
    grid = np.full((len(models), len(illusions)), np.nan)
    for r in rows:
        grid[models.index(r["model"]), illusions.index(r["illusion"])] = r["Accuracy/Gap"]
    lim = float(np.nanmax(np.abs(grid))) if np.isfinite(grid).any() else 1.0
    lim = lim or 1.0
    fig, ax = plt.subplots(figsize=(1.0 + 0.8 * max(len(illusions), 1), 1.2 + 0.5 * max(len(models), 1)))
    im = ax.imshow(np.ma.masked_invalid(grid), cmap="RdBu", vmin=-lim, vmax=lim, aspect="auto")
    for i in range(len(models)):
        for j in range(len(illusions)):
            if np.isfinite(grid[i, j]):
                ax.text(j, i, f"{grid[i, j]:.1f}", ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(illusions)), illusions, rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(len(models)), models, fontsize=8)
    fig.colorbar(im, ax=ax, label="Accuracy gap (%)")
    ax.set_title("Accuracy gap per illusion (Perturbed - Original)")
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


def worst_case_pairs(records: list[dict], k: int = 6) -> list[tuple[dict, dict]]:
    """The k (clean, perturbed) record pairs with the largest accuracy drop, one per (model, dataset, case_id),
    among pairs whose both image files exist; ties broken by key so the choice is deterministic."""
    recs = validate_records(records)
    clean = {(r["model"], r["dataset"], r["case_id"]): r for r in recs if r["severity"] == 0}
    best: dict[tuple, tuple] = {}
    missing = 0
    for r in recs:
        key = (r["model"], r["dataset"], r["case_id"])
        c = clean.get(key)
        if r["severity"] == 0 or c is None or not r.get("image") or not c.get("image"):
            continue
        if not (Path(r["image"]).is_file() and Path(c["image"]).is_file()):
            missing += 1
            continue
        drop = c["accuracy"] - r["accuracy"]
        cand = (-drop, key, r["illusion"], r["severity"])
        if key not in best or cand < best[key][0]:
            best[key] = (cand, c, r)
    if missing:
        warnings.warn(f"worst_cases: {missing} perturbed record(s) skipped, image file(s) not found")
    chosen = sorted(best.values(), key=lambda t: t[0])[:k]
    return [(c, r) for _, c, r in chosen]


def worst_cases(records: list[dict], path: str | Path, k: int = 6) -> Path | None:
    """Draw the k cases whose accuracy drops most (clean | perturbed, GT green, prediction red); None (no file)
    when no record pair has readable image paths."""
    if k < 1:
        raise ValueError(f"worst_cases: k must be >= 1, got {k}")
    pairs = worst_case_pairs(records, k)
    if not pairs:
        return None
    fig, axes = plt.subplots(len(pairs), 2, figsize=(8, 2.6 * len(pairs)), squeeze=False)
    for (c, r), row in zip(pairs, axes):
        for ax, rec, label in ((row[0], c, "original"), (row[1], r, f"{r['illusion']} s{r['severity']}")):
            ax.imshow(_draw(rec["image"], rec.get("gt_lanes"), rec.get("pred_lanes")))
            ax.set_title(f"{rec['model']} {rec['case_id']} {label}: acc {100 * rec['accuracy']:.1f}%", fontsize=8)
            ax.axis("off")
    return save_figure(fig, path)
