"""report.html of a VLM's evaluation or test: its tables, the Gap intervals, visual reliance, DriveLM and language
tables, and the worst answers beside frames of the clean and the perturbed clip, read from the clip files or
rendered again from per_answer.suite.json.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

from lanevil_train.report.page.gallery import draw_lanes, read_records, remove_stale_files, suite_file, write_jpeg
from lanevil_train.report.page.header import add_run_header, run_identities
from lanevil_train.report.page.html import FILES, GAP_LABELS, Cell, Page, _raw, esc, slug, table_html
from lanevil_train.report.page.tables import _load_rows, add_plots, add_robustness_tables, robustness_plots

# ------------------------------------------------------------------------------------------------ VLM page
ANSWER_FIELDS = ("gpt_score", "minilm_score", "correct")  # what ranks the worst answers: the judge's, else accuracy
FRAME_WIDTH = 200
STRIP_FRAMES = 3


def worst_answer_pairs(records: Sequence[dict], k: int = 12) -> tuple[str | None, list[tuple[dict, dict]]]:
    """(field, [(clean record, perturbed record)]): the k answers an illusion hurt most, by the judge's score
    (gpt_score, else minilm_score) or else by accuracy: the perturbed clip's score below the same question's on the
    clean clip, largest drop first (ties by key)."""
    field = next((f for f in ANSWER_FIELDS if any(r.get(f) is not None for r in records)), None)
    if field is None:
        return None, []
    clean = {(r["model"], r["dataset"], r["case_id"], r["qa_id"]): r for r in records if r["severity"] == 0}
    drops = []
    for r in records:
        c = clean.get((r["model"], r["dataset"], r["case_id"], r["qa_id"]))
        if r["severity"] > 0 and c is not None and r.get(field) is not None and c.get(field) is not None \
                and r[field] < c[field]:
            drops.append((c[field] - r[field], r["key"], c, r))
    return field, [(c, r) for _, _, c, r in sorted(drops, key=lambda d: (-d[0], d[1]))[:k]]


class FrameSource:
    """The frames of one VLM results file's clips: per_answer.suite.json names their files (a clip set on disk) or
    the on-the-fly suite that renders them (vlm/clips/clip_set.py description)."""

    def __init__(self, results: Path):
        described = suite_file(Path(results))
        self.description = json.loads(described.read_text(encoding="utf-8")) if described.is_file() else None
        self._suite = None
        self._index: dict[str, int] = {}

    def frames(self, clip_id: str) -> list | None:
        """The clip's frames as RGB arrays, or None when they can be neither read nor rendered."""
        d = self.description
        if d is None:
            return None
        if d.get("suite") == "clip_frames":
            from lanevil_train.data.formats import load_image

            paths = d.get("frames", {}).get(clip_id)
            try:
                return [load_image(p) for p in paths] if paths else None
            except (OSError, ValueError):
                return None
        if d.get("suite") == "synthetic_clips":
            if self._suite is None:
                from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite

                self._suite = SyntheticClipSuite.from_description(d)
                self._index = {self._suite.item_key(i): i for i in range(len(self._suite))}
            i = self._index.get(clip_id)
            return None if i is None else self._suite[i]["frames"]
        return None


def _strip(frames: list, count: int = STRIP_FRAMES) -> list:
    """`count` frames spread over the clip (first and last included)."""
    if len(frames) <= count:
        return list(frames)
    step = (len(frames) - 1) / (count - 1)
    return [frames[round(i * step)] for i in range(count)]


def _strip_html(out_dir: Path, frames: list | None, name: str, label: str) -> tuple[str, set[str]]:
    if not frames:
        return f'<div class="note">{esc(label)}: frames not available</div>', set()
    imgs, names = [], set()
    for i, frame in enumerate(_strip(frames)):
        file = f"{name}-{i}.jpg"
        w, h = write_jpeg(out_dir / FILES / file, draw_lanes(frame, None, None, FRAME_WIDTH))
        names.add(file)
        imgs.append(f'<img src="{FILES}/{esc(file)}" width="{w}" height="{h}" alt="{esc(label)} frame {i}" '
                    'loading="lazy">')
    return f'<div><div class="note">{esc(label)}</div>{"".join(imgs)}</div>', names


def write_answers_section(out_dir: Path, results: Path, k: int = 12) -> tuple[str, set[str]]:
    """The worst answers of a VLM results file beside their clips' frames (clean and perturbed, a strip of
    STRIP_FRAMES each): question, reference, both answers and both scores."""
    records = read_records(results, keep_lanes=False)
    field, pairs = worst_answer_pairs(records, k)
    if not pairs:
        return "", set()
    source = FrameSource(results)
    scale = 100.0 if field == "correct" else 1.0
    parts = [f'<p class="note">The {len(pairs)} answers an illusion hurt most, by {esc(field)} (the perturbed clip\'s '
             "answer scored below the same question's on the clean clip), largest drop first.</p>"]
    names: set[str] = set()
    frames_of: dict[str, list | None] = {}
    for c, r in sorted(pairs, key=lambda p: str(p[1].get("case_id"))):  # render base clip by base clip
        for rec in (c, r):
            clip = str(rec.get("clip_id"))
            if clip not in frames_of:
                frames_of[clip] = source.frames(clip)
    for c, r in pairs:
        strips = []
        for rec, label in ((c, "clean clip"), (r, f"{r.get('illusion')} severity {r['severity']}")):
            clip = str(rec.get("clip_id"))
            body, used = _strip_html(out_dir, frames_of.get(clip), slug(f"{rec['model']}-{clip}")[-80:], label)
            strips.append(body)
            names |= used
        drop = scale * (c[field] - r[field])
        parts.append(
            f'<figure class="pair answer" data-model="{esc(r["model"])}" data-illusion="{esc(r.get("illusion"))}" '
            f'data-case="{esc(r["case_id"])}" data-qa="{esc(r["qa_id"])}" data-severity="{r["severity"]}" '
            f'data-drop="{_raw(float(drop))}"><div class="imgs">{"".join(strips)}</div><figcaption>'
            f'<b>{esc(r.get("qa_category"))}</b> ({esc(r.get("segment") or "")}): {esc(r["question"])}<br>'
            f'reference: {esc(r["reference"])}<br>clean answer ({esc(field)} {scale * c[field]:.0f}): '
            f'{esc(c["answer"])}<br>perturbed answer ({esc(field)} {scale * r[field]:.0f}): {esc(r["answer"])}'
            "</figcaption></figure>")
    return "".join(parts), names


def fold_intervals(rows: Sequence[dict]) -> list[dict]:
    """Rows whose "<p>/low", "<p>/high" (and "<p>/distinguishable") columns become the interval of their value
    column ("<p>/gap", "<p>/reliance", "<p>/gain", or "gap" for a bare low/high), shown under it."""
    out = []
    for row in rows:
        new = dict(row)
        prefixes = {k[:-len("low")] for k in row if k.endswith("low") and f"{k[:-len('low')]}high" in row}
        for p in prefixes:
            value = next((f"{p}{v}" for v in ("gap", "reliance", "gain") if f"{p}{v}" in row), None)
            if value is None:
                continue
            new[value] = Cell(row[value], row[f"{p}low"], row[f"{p}high"],
                              mark="*" if row.get(f"{p}distinguishable") else "", key=value)
            for end in ("low", "high", "distinguishable"):
                new.pop(f"{p}{end}", None)
        out.append(new)
    return out


VLM_TABLES = (("gap_intervals", "Accuracy Gap with intervals (yes/no and choice questions)"),
              ("visual_reliance", "Visual reliance beside the blind baselines"),
              ("drivelm_score", "DriveLM's challenge score"), ("language_scores", "Language scores"))


def write_vlm_page(out_dir: str | Path, result_files: Sequence[Path], k: int = 12) -> Path:
    """report.html of a VLM evaluation (or a VLM's test after training): header, the robustness tables of
    report.md (main, per type, per severity, per QA category and segment, relative), the Gap intervals, visual
    reliance, DriveLM and language tables where the run wrote them, the plots, and the worst answers beside their
    clips' frames (the first results file's: the model's, not a blind baseline's)."""
    from lanevil_train.report.specs import VQA_SPEC

    out_dir = Path(out_dir)
    result_files = [Path(p) for p in result_files]
    page = Page("VLM robustness report")
    add_run_header(page, out_dir, run_identities(result_files))
    add_robustness_tables(page, out_dir, VQA_SPEC)
    for name, title in VLM_TABLES:
        rows = _load_rows(out_dir, name)
        if rows:
            rows = [{k: v for k, v in row.items() if not isinstance(v, (list, dict)) and not k.endswith("_note")}
                    for row in rows]
            page.add_section(title, table_html(fold_intervals(rows), f"table-{name}",
                                               gap_columns=lambda c: c.label in (*GAP_LABELS, "gap", "reliance")),
                             name)
    add_plots(page, out_dir, robustness_plots(out_dir))
    keep: set[str] = set()
    if result_files:
        body, keep = write_answers_section(out_dir, result_files[0], k)
        if body:
            page.add_section("Worst answers", body, "answers")
    path = page.write(out_dir)
    remove_stale_files(out_dir, keep)
    return path
