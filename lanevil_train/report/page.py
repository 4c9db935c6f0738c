"""report.html: one self-contained page per run, beside report.md, made from the run's record and table files.

What the page holds (each from files the run already wrote, never from a model):

- a header: the model(s), each one's weights sha256 (the hash of the network's state dict that streaming wrote to
  <results>.run.json beside its per_image.jsonl) and checkpoint (ckpt_path of the run's config, when the run read
  one), the command line (Hydra's .hydra/overrides.yaml in the run folder or the one above it, else sys.argv), the
  package version and the date the page was written;
- the tables of report.md, from the same rows (main.json, per_type.json, ... as report/robustness.py wrote them):
  columns named "<group>/<name>" are grouped under one header cell (a two-row <thead>, colspan), so every score's
  Perturbed / Original / Gap sit side by side; each Gap (and a defense's gain) is coloured by its sign and size (red:
  worse than the reference, blue: better, deeper the larger, whichever way the score points); intervals and
  mean ± std are shown under the value where the rows carry them (seeds, a compare's bootstrap gains);
- the run's PNG plots (score vs severity, the type x severity heatmap, gain bars), as <img> with paths relative to
  the page;
- for lane detectors, a gallery per illusion type: the images that illusion hurt most (the largest drop of the
  per-image headline score from the same case's clean image, one image per case, at most `per_type`, only drops
  > 0), each drawn clean | perturbed with the true lanes (green) and the predicted lanes (red) of the records, and
  the per-image scores under them. The images are read from the record's `image` path (a set written by
  task=build), or rendered again from the suite's description (per_image.suite.json beside per_image.jsonl, written
  by an on-the-fly suite: data/suites.py SyntheticIllusionSuite.description), and written as small JPEGs (480 px
  wide) into report_files/ beside the page.

For machines reading it (the browser test): every table has id "table-<name>" (<name>: its JSON file's stem, e.g.
table-main), every numeric cell a data-value attribute with the raw number (NaN written "NaN"; an interval's ends in
data-low / data-high), the cells of table-main a data-key naming their column of main.json; clicking a header cell
sorts its table by that column (numbers numerically, missing values last; again to reverse; aria-sort says how).
Gallery figures carry data-model, data-illusion, data-case, data-severity and data-drop.

The same builder makes the other runs' pages, each with its own sections: write_vlm_page (a VLM's evaluation or
test: its tables, the Gap intervals, visual reliance, DriveLM and language tables, and the worst answers beside
frames of the clean and the perturbed clip, read from the clip files or rendered again from per_answer.suite.json),
write_compare_page (task=compare: gains over `none` with their intervals, scores per defense, links to each run's
page) and write_closed_loop_page (task=closed_loop: ASR with Wilson intervals, collisions, time to collision and
departure, the ASR and deviation plots, worst_run.gif).

The page needs nothing from elsewhere: no CDN, font, script or style is fetched (the script and style are inline)
and it opens from disk with no server. It is written atomically, so a resumed run rewrites it whole, and the JPEGs
of report_files/ that the new page no longer shows are removed.
"""

from __future__ import annotations

import datetime
import hashlib
import html
import json
import math
import re
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

from lanevil_train.files.atomic import atomic_write_bytes, atomic_write_text

LANE_FIELDS = ("pred_lanes", "gt_lanes")  # evaluation/lane_records.py's (read here without importing Lightning)
PAGE = "report.html"
FILES = "report_files"
SUITE_FILE_SUFFIX = ".suite.json"  # per_image.suite.json: how to render an on-the-fly suite's images again
IMAGE_WIDTH = 480
PER_TYPE = 4
JPEG_QUALITY = 82


# ------------------------------------------------------------------------------------------------------ cells
@dataclass(frozen=True)
class Cell:
    """A table value with what the page shows around it: an interval (low, high), a sample std, a mark (e.g. "*"
    for a gain told apart from zero), and the source column it came from (data-key)."""

    value: object
    low: float | None = None
    high: float | None = None
    std: float | None = None
    mark: str = ""
    key: str | None = None
    href: str | None = None  # a link (relative to the page) around the value


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _number_text(value) -> str:
    if isinstance(value, float):
        return "n/a" if math.isnan(value) else f"{value:.2f}"
    return str(value)


def _raw(value) -> str:
    """A number as data-value carries it: repr of the float (exact), NaN as "NaN"."""
    if isinstance(value, float):
        return "NaN" if math.isnan(value) else repr(value)
    return str(value)


def esc(text) -> str:
    return html.escape(str(text), quote=True)


def slug(text: str) -> str:
    """A string as an id / file name part: letters, digits, - and _ only."""
    return re.sub(r"[^A-Za-z0-9_-]+", "-", str(text)).strip("-") or "x"


# ---------------------------------------------------------------------------------------------------- columns
@dataclass(frozen=True)
class Column:
    key: str
    group: str | None
    label: str


def columns_of(rows: Sequence[dict]) -> list[Column]:
    """The rows' columns (every key, first-seen order), "<group>/<name>" ones grouped: columns of one group are
    put together where their group first appears, so a group is one header cell."""
    keys = list(dict.fromkeys(k for row in rows for k in row))
    first: dict[str, int] = {}
    cols = []
    for i, key in enumerate(keys):
        group, _, label = key.rpartition("/")
        group = group or None
        anchor = first.setdefault(group, i) if group is not None else i
        cols.append((anchor, i, Column(key, group, label if group else key)))
    return [c for _, _, c in sorted(cols, key=lambda t: (t[0], t[1]))]


def perturbed_named(rows: Sequence[dict], scores: Iterable[str]) -> list[dict]:
    """Rows whose bare score columns (per_severity's "Accuracy", beside "Accuracy/Original") renamed
    "<score>/Perturbed", so the three sit under one header."""
    scores = set(scores)
    out = []
    for row in rows:
        out.append({(f"{k}/Perturbed" if k in scores and f"{k}/Gap" in row else k): v for k, v in row.items()})
    return out


# ------------------------------------------------------------------------------------------------------ tables
GAP_LABELS = ("Gap", "gain", "Gap vs first", "Gap vs second")


def _gap_scale(rows: Sequence[dict], col: Column) -> float:
    values = [abs(_value(row.get(col.key))) for row in rows if _is_number(_value(row.get(col.key)))]
    values = [v for v in values if not math.isnan(v)]
    return max([2.0, *values])


def _value(cell):
    return cell.value if isinstance(cell, Cell) else cell


def _gap_style(value: float, scale: float, higher_is_better: bool) -> tuple[str, str]:
    """(class, inline style) of a Gap cell: red when worse than the reference, blue when better, alpha by size."""
    if not _is_number(value) or math.isnan(value) or value == 0:
        return "gap", ""
    worse = (value < 0) == higher_is_better
    alpha = 0.12 + 0.6 * min(1.0, abs(value) / scale)
    rgb = "214, 39, 40" if worse else "31, 119, 180"
    return f"gap {'worse' if worse else 'better'}", f"background: rgba({rgb}, {alpha:.2f})"


def table_html(rows: Sequence[dict], table_id: str, caption: str | None = None,
               lower_is_better: Iterable[str] = (), gap_columns: Callable[[Column], bool] | None = None) -> str:
    """A sortable table of the rows: grouped two-row header, numbers right-aligned with data-value, Gap cells
    coloured. `lower_is_better`: score names (a group or a column label) whose Gap is good when negative;
    `gap_columns`: which columns are coloured as gaps (default: those labelled Gap or gain)."""
    if not rows:
        return f'<p class="empty" id="{esc(table_id)}">(no rows)</p>'
    lower = set(lower_is_better)
    cols = columns_of(rows)
    is_gap = gap_columns or (lambda c: c.label in GAP_LABELS)
    scales = {c.key: _gap_scale(rows, c) for c in cols if is_gap(c)}
    grouped = any(c.group is not None for c in cols)
    head = ["<thead>"]
    top, bottom = ["<tr>"], ["<tr>"]
    i = 0
    while i < len(cols):
        c = cols[i]
        if c.group is None:
            span = ' rowspan="2"' if grouped else ""
            top.append(f'<th scope="col" data-col="{i}"{span}>{esc(c.label)}</th>')
            i += 1
            continue
        j = i
        while j < len(cols) and cols[j].group == c.group:
            bottom.append(f'<th scope="col" data-col="{j}">{esc(cols[j].label)}</th>')
            j += 1
        top.append(f'<th scope="colgroup" colspan="{j - i}" class="group">{esc(c.group)}</th>')
        i = j
    head.append("".join(top) + "</tr>")
    if grouped:
        head.append("".join(bottom) + "</tr>")
    head.append("</thead>")
    body = ["<tbody>"]
    for n, row in enumerate(rows):
        cells = []
        for c in cols:
            cell = row.get(c.key, "")
            cells.append(_cell_html(cell, c, scales.get(c.key), lower))
        body.append(f'<tr data-index="{n}">' + "".join(cells) + "</tr>")
    body.append("</tbody>")
    cap = f"<caption>{esc(caption)}</caption>" if caption else ""
    return (f'<div class="scroll"><table class="sortable" id="{esc(table_id)}">{cap}' + "".join(head)
            + "".join(body) + "</table></div>")


def _direction(col: Column, lower: set[str]) -> bool:
    """Whether the column's score is higher-is-better (its group or label not among `lower`)."""
    names = {col.label, col.group or "", *(col.group or "").split("/")}
    return not (names & lower)


def _cell_html(cell, col: Column, scale: float | None, lower: set[str]) -> str:
    info = cell if isinstance(cell, Cell) else Cell(cell)
    value = info.value
    attrs, classes, style = [], [], ""
    if info.key is not None:
        attrs.append(f'data-key="{esc(info.key)}"')
    if isinstance(value, bool):
        text = "yes" if value else "no"
    elif _is_number(value):
        classes.append("num")
        attrs.append(f'data-value="{_raw(value)}"')
        text = _number_text(value)
        if isinstance(value, float) and not math.isnan(value) and scale is not None:
            text = f"{value:+.2f}"
        if scale is not None:
            gap_class, style = _gap_style(value, scale, _direction(col, lower))
            classes.append(gap_class)
    elif isinstance(value, (list, dict)):
        text = json.dumps(value)
    elif value is None:
        text = ""
    else:
        text = str(value)
    extra = ""
    if info.low is not None and info.high is not None:
        attrs += [f'data-low="{_raw(float(info.low))}"', f'data-high="{_raw(float(info.high))}"']
        if not (math.isnan(info.low) or math.isnan(info.high)):
            extra = f'<span class="ci">[{info.low:+.2f}, {info.high:+.2f}]</span>'
    if info.std is not None:
        attrs.append(f'data-std="{_raw(float(info.std))}"')
        if not math.isnan(info.std):
            extra = f'<span class="ci">± {info.std:.2f}</span>'
    mark = f'<span class="mark">{esc(info.mark)}</span>' if info.mark else ""
    cls = f' class="{" ".join(classes)}"' if classes else ""
    sty = f' style="{style}"' if style else ""
    shown = f'<a href="{esc(info.href)}">{esc(text)}</a>' if info.href else esc(text)
    return f"<td{cls}{sty}{' ' if attrs else ''}{' '.join(attrs)}>{shown}{mark}{extra}</td>"


# ------------------------------------------------------------------------------------------------------- page
CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1400px;padding:1rem 2rem;
color:#222;background:#fff;line-height:1.4}
h1{font-size:1.6rem;margin-bottom:.2rem}h2{margin-top:2rem;border-bottom:1px solid #ddd;padding-bottom:.2rem}
header dl{display:grid;grid-template-columns:max-content 1fr;gap:.15rem 1rem;margin:.5rem 0}
header dt{font-weight:600;color:#555}header dd{margin:0;word-break:break-all}
code{font-family:ui-monospace,SFMono-Regular,Menlo,Consolas,monospace;font-size:.9em;background:#f4f4f4;padding:0 .2em}
nav ul{columns:3;list-style:none;padding:0}
.scroll{overflow-x:auto;margin:.5rem 0 1rem}
table{border-collapse:collapse;font-size:.85rem}
caption{text-align:left;font-weight:600;padding:.3rem 0}
th,td{border:1px solid #ccc;padding:.2rem .45rem;white-space:nowrap}
thead th{background:#f3f3f3;cursor:pointer;user-select:none}thead th.group{cursor:default;background:#e8e8e8}
thead th[aria-sort=ascending]::after{content:" \\25B2"}thead th[aria-sort=descending]::after{content:" \\25BC"}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.ci{display:block;font-size:.75em;color:#555}.mark{font-weight:700;margin-left:.15em}
.note{color:#555;font-size:.9rem}
.plots img{max-width:100%;height:auto;border:1px solid #eee;margin:.3rem 0}
.gallery{display:flex;flex-wrap:wrap;gap:1rem}
figure.pair{margin:0;border:1px solid #ddd;padding:.4rem;background:#fafafa;max-width:980px}
figure.pair .imgs{display:flex;gap:.3rem;flex-wrap:wrap}
figure.pair img{max-width:100%;height:auto}
figure.pair figcaption{font-size:.8rem;margin-top:.3rem}
.sw{display:inline-block;width:.9em;height:.9em;vertical-align:-.1em;margin:0 .2em}
"""

SCRIPT = """
(function(){
  function key(cell){
    if(!cell){return {missing:1};}
    var raw=cell.getAttribute('data-value');
    if(raw!==null){var n=Number(raw);return isNaN(n)?{missing:1}:{missing:0,num:true,v:n};}
    var t=cell.textContent.trim();
    return t===''?{missing:1}:{missing:0,num:false,v:t};
  }
  function compare(a,b,asc){
    if(a.missing||b.missing){return a.missing-b.missing;}
    var c=(a.num&&b.num)?a.v-b.v:String(a.v).localeCompare(String(b.v),undefined,{numeric:true});
    return asc?c:-c;
  }
  function sortBy(table,th){
    var col=Number(th.getAttribute('data-col'));
    var body=table.tBodies[0];
    var rows=Array.prototype.slice.call(body.rows);
    var asc=th.getAttribute('aria-sort')!=='ascending';
    Array.prototype.forEach.call(table.querySelectorAll('thead th'),function(h){h.removeAttribute('aria-sort');});
    th.setAttribute('aria-sort',asc?'ascending':'descending');
    rows.sort(function(r,s){
      return compare(key(r.cells[col]),key(s.cells[col]),asc)||(Number(r.getAttribute('data-index'))-
        Number(s.getAttribute('data-index')));
    });
    rows.forEach(function(r){body.appendChild(r);});
  }
  Array.prototype.forEach.call(document.querySelectorAll('table.sortable'),function(table){
    Array.prototype.forEach.call(table.querySelectorAll('thead th[data-col]'),function(th){
      th.addEventListener('click',function(){sortBy(table,th);});
    });
  });
})();
"""


class Page:
    """An HTML page being put together: a header, then sections of tables, plots and galleries."""

    def __init__(self, title: str):
        self.title = title
        self.header: list[tuple[str, str]] = []  # (label, html)
        self.sections: list[tuple[str, str, str]] = []  # (id, title, html)

    def add_header(self, label: str, value_html: str) -> None:
        self.header.append((label, value_html))

    def add_section(self, title: str, body_html: str, section_id: str | None = None) -> None:
        self.sections.append((section_id or slug(title).lower(), title, body_html))

    def html(self) -> str:
        nav = "".join(f'<li><a href="#{esc(sid)}">{esc(title)}</a></li>' for sid, title, _ in self.sections)
        header = "".join(f"<dt>{esc(label)}</dt><dd>{value}</dd>" for label, value in self.header)
        sections = "".join(f'<section id="{esc(sid)}"><h2>{esc(title)}</h2>{body}</section>'
                           for sid, title, body in self.sections)
        return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
                f"<title>{esc(self.title)}</title><style>{CSS}</style></head><body>"
                f"<header><h1>{esc(self.title)}</h1><dl>{header}</dl></header>"
                f"<nav><ul>{nav}</ul></nav><main>{sections}</main>"
                f"<script>{SCRIPT}</script></body></html>\n")

    def write(self, out_dir: str | Path) -> Path:
        path = Path(out_dir) / PAGE
        atomic_write_text(path, self.html())
        return path


def plots_html(out_dir: Path, names: Iterable[str]) -> str:
    """<img> of each PNG of out_dir named (those that exist), paths relative to the page."""
    parts = [f'<figure><img src="{esc(name)}" alt="{esc(Path(name).stem)}" loading="lazy">'
             f"<figcaption class=\"note\">{esc(Path(name).stem.replace('_', ' '))}</figcaption></figure>"
             for name in names if (out_dir / name).is_file()]
    return f'<div class="plots">{"".join(parts)}</div>' if parts else ""


GAP_LEGEND = ('<p class="note">Gap = Perturbed - Original; coloured <span class="sw" style="background:'
              'rgba(214,39,40,.6)"></span>worse than the original, <span class="sw" style="background:'
              'rgba(31,119,180,.6)"></span>better, deeper the larger. Click a column header to sort.</p>')


# ------------------------------------------------------------------------------------------------------ header
def command_line(out_dir: str | Path) -> str:
    """The command that made the run: Hydra's .hydra/overrides.yaml in out_dir or its parent (a training run's
    robustness/), else this process's sys.argv."""
    out_dir = Path(out_dir)
    for folder in (out_dir, out_dir.parent):
        overrides = folder / ".hydra" / "overrides.yaml"
        if overrides.is_file():
            from omegaconf import OmegaConf

            try:
                values = OmegaConf.to_container(OmegaConf.load(overrides))
            except Exception:  # noqa: BLE001 -- a header line is not worth failing a run for
                continue
            if isinstance(values, list):
                return "python -m lanevil_train " + " ".join(shlex.quote(str(v)) for v in values)
    argv = list(sys.argv)
    if argv and argv[0].replace("\\", "/").endswith("lanevil_train/__main__.py"):
        return "python -m lanevil_train " + " ".join(shlex.quote(a) for a in argv[1:])
    return " ".join(shlex.quote(a) for a in argv)


def _run_config_value(results: Path, key: str):
    """`key` of the config nearest above a results file (.hydra/config.yaml or a compare run's config.yaml)."""
    from omegaconf import OmegaConf

    for folder in (results.parent, results.parent.parent):
        for config in (folder / ".hydra" / "config.yaml", folder / "config.yaml"):
            if config.is_file():
                try:
                    return OmegaConf.select(OmegaConf.load(config), key)
                except Exception:  # noqa: BLE001
                    return None
    return None


def run_identities(result_files: Sequence[Path], labels: dict[Path, str] | None = None) -> list[dict]:
    """Per results file: its model label, the weights hash its <stem>.run.json holds, the run's ckpt_path."""
    labels = labels or {}
    out = []
    for path in map(Path, result_files):
        marker = path.with_name(f"{path.stem}.run.json")
        identity = {}
        if marker.is_file():
            try:
                identity = json.loads(marker.read_text(encoding="utf-8"))
            except ValueError:
                identity = {}
        model = labels.get(path) or identity.get("model")
        if model is None:
            try:
                with open(path, encoding="utf-8") as handle:
                    model = json.loads(handle.readline()).get("model")
            except (OSError, ValueError):
                model = None
        out.append({"model": model, "dataset": identity.get("dataset"),
                    "weights_sha256": identity.get("weights_sha256"),
                    "checkpoint": _run_config_value(path, "ckpt_path") or identity.get("vlm.path"),
                    "results": str(path)})
    return out


def add_run_header(page: Page, out_dir: Path, identities: Sequence[dict] = (), models: Sequence[str] = ()) -> None:
    """The header lines every page has: models (with weights hash and checkpoint where known), command, version,
    date."""
    from lanevil_train import __version__

    lines = []
    seen = set()
    for ident in identities:
        if ident.get("model") is None or (ident["model"], ident.get("dataset")) in seen:
            continue
        seen.add((ident["model"], ident.get("dataset")))
        bits = [f"<b>{esc(ident['model'])}</b>"]
        if ident.get("dataset"):
            bits.append(f"on {esc(ident['dataset'])}")
        if ident.get("weights_sha256"):
            bits.append(f"weights sha256 <code>{esc(ident['weights_sha256'])}</code>")
        if ident.get("checkpoint"):
            bits.append(f"checkpoint <code>{esc(ident['checkpoint'])}</code>")
        lines.append(" · ".join(bits))
    known = {ident.get("model") for ident in identities}
    lines += [f"<b>{esc(m)}</b>" for m in models if m not in known]
    if lines:
        page.add_header("models", "<br>".join(lines))
    page.add_header("command", f"<code>{esc(command_line(out_dir))}</code>")
    page.add_header("lanevil_train", esc(__version__))
    page.add_header("written", esc(datetime.datetime.now().astimezone().isoformat(timespec="seconds")))


# ---------------------------------------------------------------------------------------------- lane tables
def _load_rows(out_dir: Path, name: str) -> list[dict] | None:
    path = out_dir / f"{name}.json"
    if not path.is_file():
        return None
    rows = json.loads(path.read_text(encoding="utf-8"))
    return rows if isinstance(rows, list) else None


def main_long_cells(main_rows: Sequence[dict]) -> list[dict]:
    """main.json's wide rows (one per model) as one row per (model, category) with "<score>/<kind>" cells, each a
    Cell naming its main.json column (data-key)."""
    out = []
    for row in main_rows:
        by_group: dict[str, dict] = {}
        for key, value in row.items():
            if key.count("/") == 2:
                group, score, kind = key.split("/")
                by_group.setdefault(group, {})[f"{score}/{kind}"] = Cell(value, key=key)
        out += [{"model": row["model"], "category": group, **cells} for group, cells in by_group.items()]
    return out


# the tables of report.md, in its order: (JSON stem, title); per_<field> tables are found by their files
TABLES = (("main", "Robustness per category"), ("per_type", "Per illusion type"),
          ("per_severity", "Per severity level"))
LATER_TABLES = (("relative", "Relative robustness"),)


def _lower(spec) -> list[str]:
    return [s.name for s in spec.scores if not s.higher_is_better] if spec is not None else []


def add_robustness_tables(page: Page, out_dir: Path, spec=None) -> None:
    """The tables write_report wrote (main, per type, per severity, per group field, relative, combined) as
    sections, from their JSON files."""
    lower = _lower(spec)
    scores = [s.name for s in spec.scores] if spec is not None else []
    summary = _load_rows(out_dir, "test_scores")
    if summary:
        page.add_section("Scores", table_html(summary, "table-test_scores",
                                              caption="Headline scores per model, dataset and kind of image"),
                         "scores")
    names = [*TABLES, *[(p.stem, "Per " + p.stem[4:].replace("_", " ")) for p in sorted(out_dir.glob("per_*.json"))
                        if p.stem not in dict(TABLES) and "." not in p.stem], *LATER_TABLES,
             ("combined", "Combined illusions")]
    unit = spec.unit if spec is not None else "%"
    for name, title in names:
        rows = _load_rows(out_dir, name)
        if rows is None:
            continue
        if name == "main":
            body = GAP_LEGEND + table_html(main_long_cells(rows), "table-main", lower_is_better=lower,
                                           caption=f"Perturbed / Original / Gap per category ({unit}); average = "
                                                   f"mean of the categories")
        else:
            body = table_html(perturbed_named(rows, scores), f"table-{name}", lower_is_better=lower)
        page.add_section(title, body, name)


def add_plots(page: Page, out_dir: Path, names: Iterable[str], title: str = "Plots") -> None:
    body = plots_html(out_dir, names)
    if body:
        page.add_section(title, body, "plots")


def robustness_plots(out_dir: Path) -> list[str]:
    """The PNGs write_report draws that the page shows (score vs severity, the gap heatmap), seeds' gain bars."""
    return ([p.name for p in sorted(out_dir.glob("*_vs_severity.png"))] + ["gap_heatmap.png"]
            + [p.name for p in sorted(out_dir.glob("seed_gains*.png"))])


# --------------------------------------------------------------------------------------------------- seeds
def add_seed_tables(page: Page, out_dir: Path, spec=None) -> None:
    """seeds.json (mean ± std over seeds) and seed_gains.json (gains with their intervals) as pivot tables: a row
    per model, a column per category."""
    scores_rows, gains = _load_rows(out_dir, "seeds"), _load_rows(out_dir, "seed_gains") or []
    if not scores_rows:
        return
    lower = _lower(spec)
    parts = []
    for dataset in dict.fromkeys(r["dataset"] for r in scores_rows):
        mine = [r for r in scores_rows if r["dataset"] == dataset]
        names = [k for k in mine[0] if f"{k}/std" in mine[0]]
        for score in names:
            table = [{"model": name, **{r["category"]: Cell(r[score], std=r[f"{score}/std"]) for r in mine
                                        if r["name"] == name}} for name in dict.fromkeys(r["name"] for r in mine)]
            parts.append(table_html(table, f"table-seeds-{slug(dataset)}-{slug(score)}",
                                    caption=f"{dataset}: {score}, mean ± std over seeds"))
        mine_gains = [r for r in gains if r["dataset"] == dataset]
        for score in names:
            if not mine_gains or f"{score}/gain" not in mine_gains[0]:
                continue
            table = [{"model": name, **{r["category"]: Cell(r[f"{score}/gain"], r[f"{score}/low"], r[f"{score}/high"],
                                                           mark="*" if r[f"{score}/distinguishable"] else "")
                                        for r in mine_gains if r["name"] == name}}
                     for name in dict.fromkeys(r["name"] for r in mine_gains)]
            parts.append(table_html(table, f"table-seed_gains-{slug(dataset)}-{slug(score)}",
                                    caption=f"{dataset}: {score} gain over the reference (points), interval; * "
                                            f"excludes zero", lower_is_better=lower,
                                    gap_columns=lambda c: c.key != "model"))
    page.add_section("Seeds", "".join(parts), "seeds")


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


# ---------------------------------------------------------------------------------------------- lane page
def write_robustness_page(out_dir: str | Path, result_files: Sequence[Path], rs=None,
                          labels: dict[Path, str] | None = None, per_type: int = PER_TYPE,
                          title: str = "Robustness report") -> Path:
    """report.html of a run whose report.md write_report (report/robustness.py) wrote in out_dir: header, its
    tables and plots, seeds (when task=report wrote seeds.json), and for lane detectors the gallery. `rs`: the
    run's record set when the caller has it (else the results files are read again, without lanes)."""
    from lanevil_train.report.specs import record_set

    out_dir = Path(out_dir)
    result_files = [Path(p) for p in result_files]
    labels = labels or {}
    if rs is None:
        records = [{**r, **({"model": labels[p]} if p in labels else {})} for p in result_files
                   for r in read_records(p, keep_lanes=False)]
        rs = record_set(records)
    page = Page(title)
    add_run_header(page, out_dir, run_identities(result_files, labels), rs.models)
    add_robustness_tables(page, out_dir, rs.spec)
    add_seed_tables(page, out_dir, rs.spec)
    add_plots(page, out_dir, robustness_plots(out_dir))
    keep: set[str] = set()
    if rs.spec.name == "lane" and any(r["severity"] > 0 for r in rs.records):
        body, keep = write_gallery(out_dir, rs, result_files, labels, per_type)
        if body:
            page.add_section("Gallery", body, "gallery")
    elif rs.spec.name == "vqa" and result_files:  # task=report over VLM runs: the first run's worst answers
        body, keep = write_answers_section(out_dir, result_files[0])
        if body:
            page.add_section("Worst answers", body, "answers")
    path = page.write(out_dir)
    remove_stale_files(out_dir, keep)
    return path


# ------------------------------------------------------------------------------------------- compare page
def write_compare_page(out_dir: str | Path, score_rows: Sequence[dict], gain_rows: Sequence[dict], spec,
                       runs: dict | None = None, note: str | None = None, result_files: Sequence[Path] = ()) -> Path:
    """report.html beside compare.md (task=compare), from the rows compare.md is made of (defense_scores,
    defense_gain with their bootstrap intervals): the best defense, a gain table per score (a row per defense, a
    column per category, each gain with its interval), the scores per defense (mean ± std over seeds), the gain
    plot and the runs, each linked to its own report.html where it has one. `result_files`: the runs' results
    files, for the header's model lines (weights hashes)."""
    from lanevil_train.report.defenses import REFERENCE, _score_names, best_defense, gain_pivot, headline_of

    out_dir = Path(out_dir)
    page = Page("Defense comparison")
    add_run_header(page, out_dir, run_identities(list(result_files)),
                   list(dict.fromkeys(str(r.get("model")) for r in score_rows)))
    lower = _lower(spec)
    headline = headline_of(list(score_rows), spec).name
    best, value = best_defense(list(score_rows), spec)
    intro = (f"<p>Best average perturbed {esc(headline)}: <b>{esc(best)}</b> ({value:.2f}{esc(spec.unit)}). Gains "
             f"in points: defense minus {esc(REFERENCE)}, on the same suite; original = the suite's clean items.</p>")
    if note:
        intro += f'<p class="note">{esc(note)}</p>'
    page.add_section("Summary", intro, "summary")
    names = _score_names(score_rows[0]) if score_rows else []
    by_cell = {(r["defense"], r["category"]): r for r in gain_rows}
    parts = []
    for name in names:
        table = []
        for row in gain_pivot(list(gain_rows), name):
            cells = {"defense": row["defense"]}
            for group, gain in row.items():
                if group == "defense":
                    continue
                full = by_cell.get((row["defense"], group), {})
                low, high = full.get(f"{name}/low"), full.get(f"{name}/high")
                cells[group] = Cell(gain, low, high, mark="*" if full.get(f"{name}/distinguishable") else "")
            table.append(cells)
        parts.append(table_html(table, f"table-gain-{slug(name)}", caption=f"{name} gain over {REFERENCE} (points)"
                                + (" [interval]; * excludes zero" if any(f"{name}/low" in r for r in gain_rows)
                                   else ""),
                                lower_is_better=[name] if name in lower else [],
                                gap_columns=lambda c: c.key != "defense"))
    page.add_section("Gains over " + REFERENCE, GAP_LEGEND.replace("Gap = Perturbed - Original; coloured",
                                                                  "Gain coloured") + "".join(parts), "gains")
    shown = []
    for row in score_rows:
        cells = {}
        for key, v in row.items():
            if key.endswith("/std"):
                continue
            std = row.get(f"{key}/std")
            cells[key] = Cell(v, std=std, key=key) if std is not None else Cell(v, key=key)
        shown.append(cells)
    page.add_section("Scores per defense", table_html(shown, "table-defense_scores", lower_is_better=lower,
                                                      caption="Perturbed per category and average; original = "
                                                              "clean"), "scores")
    add_plots(page, out_dir, ["defense_gain.png"])
    if runs:
        listed = []
        for defense, by_seed in runs.items():
            for seed, run in (by_seed.items() if isinstance(by_seed, dict) else [(None, by_seed)]):
                pages = [p for p in (Path(run) / "robustness" / PAGE, Path(run) / "test" / PAGE) if p.is_file()]
                href = _relative(pages[0], out_dir) if pages else None
                listed.append({"defense": defense, **({"seed": seed} if seed is not None else {}),
                               "run": Cell(str(run), href=href)})
        page.add_section("Runs", '<p class="note">Each run links to its own page where it wrote one.</p>'
                         + table_html(listed, "table-runs"), "runs")
    return page.write(out_dir)


def _relative(target: Path, base: Path) -> str:
    """target's path relative to the folder base, with / separators (a link on the page)."""
    import os

    return Path(os.path.relpath(Path(target).resolve(), Path(base).resolve())).as_posix()


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
    add_plots(page, out_dir, ["asr.png", "deviation.png", "worst_run.gif"])
    return page.write(out_dir)
