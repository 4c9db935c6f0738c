"""The page-building primitives of report.html: cells, columns, tables, the page itself and its plots.

Tables: columns named "<group>/<name>" are grouped under one header cell (a two-row <thead>, colspan), so every
score's Perturbed / Original / Gap sit side by side; each Gap (and a defense's gain) is coloured by its sign and size
(red: worse than the reference, blue: better, deeper the larger, whichever way the score points); intervals and
mean ± std are shown under the value where the rows carry them (seeds, a compare's bootstrap gains).

For machines reading it (the browser test): every table has id "table-<name>" (<name>: its JSON file's stem, e.g.
table-main), every numeric cell a data-value attribute with the raw number (NaN written "NaN"; an interval's ends in
data-low / data-high), the cells of table-main a data-key naming their column of main.json; clicking a header cell
sorts its table by that column (numbers numerically, missing values last; again to reverse; aria-sort says how).

The page needs nothing from elsewhere: no CDN, font, script or style is fetched (the script and style, CSS and
SCRIPT here, are inline) and it opens from disk with no server. It is written atomically, so a resumed run rewrites
it whole. Plots are the run's PNGs, as <img> with paths relative to the page.
"""

from __future__ import annotations

import html
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

from lanevil_train.files.atomic import atomic_write_text

PAGE = "report.html"
FILES = "report_files"


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
