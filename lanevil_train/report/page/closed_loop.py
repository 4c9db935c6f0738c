"""report.html of task=closed_loop: ASR with Wilson intervals, collisions, time to collision and departure, the
ASR and deviation plots, worst_run.gif.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

from lanevil_train.report.page.header import add_run_header
from lanevil_train.report.page.html import Cell, Page, esc, table_html
from lanevil_train.report.page.tables import _load_rows, add_plots

# ------------------------------------------------------------------------------------------ closed-loop page
# report/closed_loop.py's rows give each rate's Wilson interval as text in a column of its own: the value it bounds
CLOSED_LOOP_INTERVALS = {"95% CI": "ASR (%)", "clean 95% CI": "clean ASR (%)", "twin 95% CI": "ASR vs twin (%)"}
_INTERVAL = re.compile(r"^\[\s*(-?[\d.]+|nan),\s*(-?[\d.]+|nan)\s*\]$")


def fold_text_intervals(rows: Sequence[dict], pairs: dict[str, str]) -> list[dict]:
    """Rows whose interval columns ("[low, high]" text, `pairs`: interval column -> the value column it bounds)
    become the interval of their value's cell."""
    out = []
    for row in rows:
        new = dict(row)
        for ci, value in pairs.items():
            match = _INTERVAL.match(str(row.get(ci, "")))
            if value in row and match:
                new[value] = Cell(row[value], float(match.group(1)), float(match.group(2)), key=value)
                new.pop(ci)
        out.append(new)
    return out


def _closed_loop_models(out_dir: Path) -> list[dict]:
    """The driven models' checkpoints from the run's config (ckpt_path, or task.models' label: checkpoint)."""
    from omegaconf import OmegaConf

    for config in (out_dir / ".hydra" / "config.yaml", out_dir.parent / ".hydra" / "config.yaml"):
        if config.is_file():
            try:
                cfg = OmegaConf.load(config)
                models = OmegaConf.select(cfg, "task.models")
                if models:
                    return [{"model": str(k), "checkpoint": str(v)} for k, v in OmegaConf.to_container(models).items()]
                ckpt = OmegaConf.select(cfg, "ckpt_path")
                return [{"model": OmegaConf.select(cfg, "task.label") or "model", "checkpoint": ckpt}] if ckpt else []
            except Exception:  # noqa: BLE001 -- a header line is not worth failing a run for
                return []
    return []


def _setting_text(value) -> str:
    """A setting as a person reads it: floats to 6 significant digits (45 mph, not 45.00000000000001)."""
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def write_closed_loop_page(out_dir: str | Path, settings: dict | None = None) -> Path:
    """report.html beside closed_loop.md (task=closed_loop), from the tables it wrote: the settings, the attack
    success rate (ASR) with its Wilson interval beside the clean twins', ASR vs twin, collisions and the time
    metrics (time to collision, time to departure), per category, illusion and severity (and models compared);
    the ASR bars, each category's worst run's deviation beside its clean twin, and the worst run's animation
    (worst_run.gif) when written."""
    out_dir = Path(out_dir)
    page = Page("Closed-loop robustness report")
    by_category = _load_rows(out_dir, "asr_by_category") or []
    labels = list(dict.fromkeys(r["model"] for r in by_category))
    models = _closed_loop_models(out_dir)
    if len(models) == 1 and len(labels) == 1 and models[0]["model"] == "model":
        models[0]["model"] = labels[0]  # no task.label: the tables' label (model_label's) names the checkpoint
    add_run_header(page, out_dir, models, labels)
    if settings:
        page.add_header("settings", esc(", ".join(f"{k}={_setting_text(v)}" for k, v in settings.items())))
    note = ('<p class="note">A run is an attack success when the car deviates more than the threshold from its '
            "lane's centre within the window after entering the illusion region; clean: the same starts without "
            "the illusion; intervals: Wilson 95 % over the runs (under each rate). Times are medians over the runs "
            "that collided or left the lane. Click a column header to sort.</p>")
    for name, title in (("asr_by_category", "ASR by category"), ("asr_by_illusion", "ASR by illusion"),
                        ("asr_by_severity", "ASR by severity"), ("asr_compare", "Models compared")):
        rows = _load_rows(out_dir, name)
        if rows:
            page.add_section(title, (note if name == "asr_by_category" else "")
                             + table_html(fold_text_intervals(rows, CLOSED_LOOP_INTERVALS), f"table-{name}",
                                          gap_columns=lambda c: False), name)
    add_plots(page, out_dir, ["asr.png", "deviation.png", "closed_loop_tracking.png", "worst_run.gif"])
    return page.write(out_dir)
