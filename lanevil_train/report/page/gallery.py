"""The lane detectors' gallery on report.html, per illusion type: the images that illusion hurt most (the largest
drop of the per-image headline score from the same case's clean image, one image per case, at most `per_type`, only
drops > 0), each drawn clean | perturbed with the true lanes (green) and the predicted lanes (red) of the records,
and the per-image scores under them.

The images are read from the record's `image` path (a set written by task=build), or rendered again from the
suite's description (per_image.suite.json beside per_image.jsonl, written by an on-the-fly suite: data/suites.py
SyntheticIllusionSuite.description), and written as small JPEGs (480 px wide) into report_files/ beside the page;
the JPEGs of report_files/ that a new page no longer shows are removed. Gallery figures carry data-model,
data-illusion, data-case, data-severity and data-drop.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from lanevil_train.files.atomic import atomic_write_bytes
from lanevil_train.report.page.html import FILES, _is_number, _raw, esc, slug

LANE_FIELDS = ("pred_lanes", "gt_lanes")  # evaluation/lane_records.py's (read here without importing Lightning)
SUITE_FILE_SUFFIX = ".suite.json"  # per_image.suite.json: how to render an on-the-fly suite's images again
IMAGE_WIDTH = 480
PER_TYPE = 4
JPEG_QUALITY = 82


# ------------------------------------------------------------------------------------------------- gallery
@dataclass(frozen=True)
class Pick:
    """A perturbed record and its clean twin, and how much the headline score dropped from one to the other."""

    clean: dict
    perturbed: dict
    drop: float


def gallery_picks(rs, per_type: int = PER_TYPE) -> dict[str, dict[str, list[Pick]]]:
    """{model: {illusion: picks}}: per illusion type, the perturbed images whose headline score fell most below
    their clean twin's (the same model's severity-0 record of the same item), one per case (its largest drop), only
    drops > 0, largest first (ties by record key), at most `per_type`."""
    from lanevil_train.report.records import item_of

    score = rs.headline
    sign = 1.0 if score.higher_is_better else -1.0
    out: dict[str, dict[str, list[Pick]]] = {}
    for model in rs.models:
        index = rs.by_model[model]
        best: dict[tuple, tuple] = {}
        for r in index.pert:
            clean = index.clean.get(item_of(r, rs.spec))
            if clean is None:
                continue
            drop = sign * (score.aggregate([clean]) - score.aggregate([r]))
            if not drop > 0:
                continue
            slot = (r["illusion"], r["dataset"], r["case_id"])
            cand = (-drop, str(r.get("key", "")), r["severity"])
            if slot not in best or cand < best[slot][0]:
                best[slot] = (cand, Pick(clean, r, drop))
        by_type: dict[str, list] = {}
        for (illusion, _, _), (cand, pick) in best.items():
            by_type.setdefault(illusion, []).append((cand, pick))
        out[model] = {ill: [p for _, p in sorted(by_type[ill], key=lambda t: t[0])[:per_type]]
                      for ill in rs.illusions if ill in by_type}
    return out


class ImageSource:
    """The images of one results file's records: from the record's `image` path, else rendered again from the
    suite that file's per_image.suite.json describes (an on-the-fly suite)."""

    def __init__(self, results: Path):
        self.results = Path(results)
        self._suite = None
        self._index: dict[str, int] | None = None
        described = suite_file(self.results)
        self.description = json.loads(described.read_text(encoding="utf-8")) if described.is_file() else None

    def image(self, record: dict):
        """The record's image as RGB uint8, or None when it can be neither read nor rendered."""
        from lanevil_train.data.formats import load_image

        path = record.get("image")
        if path:
            try:
                return load_image(path)
            except (OSError, ValueError):
                return None
        if self.description is None:
            return None
        if self._suite is None:
            from lanevil_train.data.suites import SyntheticIllusionSuite

            self._suite = SyntheticIllusionSuite.from_description(self.description)
            self._index = {self._suite.item_key(i): i for i in range(len(self._suite))}
        i = self._index.get(record.get("key"))
        return None if i is None else self._suite[i]["image"]


def suite_file(results: Path) -> Path:
    """Where an on-the-fly suite's description sits beside its results: per_image.jsonl -> per_image.suite.json."""
    results = Path(results)
    return results.with_name(f"{results.stem}{SUITE_FILE_SUFFIX}")


def draw_lanes(image, gt, pred, width: int = IMAGE_WIDTH):
    """RGB image scaled to at most `width` px wide, with the true lanes (green) and the predicted lanes (red) drawn
    on it (lane points in the original image's pixels)."""
    import cv2
    import numpy as np

    img = np.ascontiguousarray(image)
    scale = min(1.0, width / img.shape[1])
    if scale < 1.0:
        img = cv2.resize(img, (width, max(1, round(img.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    else:
        img = img.copy()
    thick = max(1, round(img.shape[1] / 240))
    for lanes, colour in ((gt, (0, 200, 0)), (pred, (235, 20, 20))):
        for lane in lanes or []:
            pts = np.asarray(lane, dtype=np.float64).reshape(-1, 2)
            pts = pts[(pts[:, 0] >= 0) & np.isfinite(pts).all(axis=1)]
            if len(pts) >= 2:
                cv2.polylines(img, [np.round(pts * scale * 8).astype(np.int32)], False, colour, thick, cv2.LINE_AA,
                              shift=3)
    return img


def write_jpeg(path: Path, rgb) -> tuple[int, int]:
    """Write an RGB image as a JPEG, atomically; its (width, height)."""
    import cv2

    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError(f"cannot encode {path} as JPEG")
    atomic_write_bytes(path, data.tobytes())
    return rgb.shape[1], rgb.shape[0]


def read_records(path: Path, keep_lanes: bool = True, lanes_for: set[str] | None = None) -> list[dict]:
    """A results file's complete records (evaluation/lane_records.py read_records, without its imports)."""
    from lanevil_train.results_log import ResultsLog

    return ResultsLog(path).records(drop=() if keep_lanes else LANE_FIELDS, keep_for=lanes_for)


def _image_name(model: str, dataset: str, key: str) -> str:
    digest = hashlib.sha1(f"{model}\0{dataset}\0{key}".encode()).hexdigest()[:10]
    stem = slug(Path(str(key)).with_suffix("").as_posix().replace("/", "_"))[-60:]
    return f"{stem}-{digest}.jpg"


def _scores_text(record: dict, spec) -> str:
    parts = []
    for score in spec.scores[:1]:
        parts.append(f"{score.name} {score.aggregate([record]):.1f}")
    for field in ("fp", "fn"):
        if _is_number(record.get(field)):
            parts.append(f"{field.upper()} {record[field]:.2f}")
    if _is_number(record.get("num_pred")) and _is_number(record.get("num_gt")):
        parts.append(f"lanes {record['num_pred']}/{record['num_gt']} predicted/true")
    return ", ".join(parts)


def write_gallery(out_dir: Path, rs, result_files: Sequence[Path], labels: dict[Path, str] | None = None,
                  per_type: int = PER_TYPE) -> tuple[str, set[str]]:
    """The gallery section's HTML and the report_files/ names it uses: picks (gallery_picks) drawn with their
    lanes (read again from the results files for the picked keys only), clean | perturbed."""
    labels = labels or {}
    picks = gallery_picks(rs, per_type)
    wanted = {str(r.get("key")) for by_type in picks.values() for ps in by_type.values() for p in ps
              for r in (p.clean, p.perturbed)}
    if not wanted:
        return "", set()
    found: dict[tuple, tuple[dict, ImageSource]] = {}
    for path in map(Path, result_files):
        source = ImageSource(path)
        for record in read_records(path, keep_lanes=False, lanes_for=wanted):
            if path in labels:
                record = {**record, "model": labels[path]}
            if str(record.get("key")) in wanted:
                found[(str(record["model"]), str(record["dataset"]), str(record["key"]))] = (record, source)
    files_dir = out_dir / FILES
    written: dict[tuple, tuple[str, int, int] | None] = {}

    def image_file(record: dict) -> tuple[str, int, int] | None:
        ident = (str(record["model"]), str(record["dataset"]), str(record.get("key")))
        if ident not in written:
            entry = found.get(ident)
            image = entry[1].image(entry[0]) if entry is not None else None
            if image is None:
                written[ident] = None
            else:
                name = _image_name(*ident)
                w, h = write_jpeg(files_dir / name, draw_lanes(image, entry[0].get("gt_lanes"),
                                                               entry[0].get("pred_lanes")))
                written[ident] = (f"{FILES}/{name}", w, h)
        return written[ident]

    # render case by case (an on-the-fly suite renders each scene once for its consecutive images)
    order = sorted(((m, ill, p) for m, by_type in picks.items() for ill, ps in by_type.items() for p in ps),
                   key=lambda t: (t[2].perturbed["dataset"], t[2].perturbed["case_id"], str(t[2].clean.get("key"))))
    for _, _, p in order:
        image_file(p.clean)
        image_file(p.perturbed)
    spec = rs.spec
    score = rs.headline
    parts = ['<p class="note">Per illusion type, the images it hurt most: the largest drop of the per-image '
             f"{esc(score.name)} from the same case's clean image (one image per case, at most {per_type}). "
             'True lanes <span class="sw" style="background:rgb(0,200,0)"></span>green, predicted lanes '
             '<span class="sw" style="background:rgb(235,20,20)"></span>red.</p>']
    missing = 0
    several = len(picks) > 1
    for model, by_type in picks.items():
        if several:
            parts.append(f'<h3 id="gallery-{esc(slug(model))}">{esc(model)}</h3>')
        for illusion in rs.illusions:
            ps = by_type.get(illusion)
            if not ps:
                continue
            category = ps[0].perturbed.get("category", "")
            tag = "h4" if several else "h3"
            parts.append(f'<{tag} id="gallery-{esc(slug(model))}-{esc(slug(illusion))}">{esc(illusion)} '
                         f'<small class="note">({esc(category)})</small></{tag}><div class="gallery">')
            for p in ps:
                clean, pert = image_file(p.clean), image_file(p.perturbed)
                if clean is None or pert is None:
                    missing += 1
                    continue
                r = p.perturbed
                imgs = "".join(f'<div><div class="note">{esc(label)}</div><img src="{esc(src)}" width="{w}" '
                               f'height="{h}" alt="{esc(r["case_id"])} {esc(label)}" loading="lazy"></div>'
                               for (src, w, h), label in ((clean, "original"),
                                                          (pert, f"{illusion} severity {r['severity']}")))
                caption = (f"<b>{esc(r['case_id'])}</b>, severity {r['severity']}: {esc(score.name)} drop "
                           f"{p.drop:.1f}<br>original: {esc(_scores_text(p.clean, spec))}<br>"
                           f"{esc(illusion)}: {esc(_scores_text(r, spec))}")
                parts.append(f'<figure class="pair" data-model="{esc(model)}" data-illusion="{esc(illusion)}" '
                             f'data-case="{esc(r["case_id"])}" data-severity="{r["severity"]}" '
                             f'data-drop="{_raw(float(p.drop))}"><div class="imgs">{imgs}</div>'
                             f"<figcaption>{caption}</figcaption></figure>")
            parts.append("</div>")
    if missing:
        parts.append(f'<p class="note">{missing} image pair(s) left out: their image files are gone and the suite '
                     "cannot be rendered again (no per_image.suite.json).</p>")
    names = {entry[0].split("/", 1)[1] for entry in written.values() if entry is not None}
    return "".join(parts), names


def remove_stale_files(out_dir: Path, keep: set[str]) -> None:
    """Delete the JPEGs of report_files/ that the page no longer shows (a rerun's page picks other images)."""
    folder = out_dir / FILES
    if not folder.is_dir():
        return
    for path in folder.glob("*.jpg"):
        if path.name not in keep:
            path.unlink(missing_ok=True)
