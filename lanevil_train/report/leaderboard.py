"""A leaderboard from robustness cards (report/card.py): models scored on the same suite, ranked by one score.

`write_leaderboard(cards, out, rank_by)` reads and validates every card, refuses cards of different suites (naming
the field that differs and both values: "b.json: suite.severities [1,2] differs from a.json's [1,2,3,4,5]"), ranks
the models and writes leaderboard.md, leaderboard.json and leaderboard.html (one self-contained page: no script,
font or image from elsewhere) into `out`.

rank_by (task.rank_by): null for the cards' primary score's overall Perturbed; Perturbed, Original, Gap or
RelRobustness of the primary score; "<score>/<kind>" for another score of the cards (F1/Gap); mCE or relative_mCE
(against the cards' common reference model, lower is better); ASR or collisions (closed loop, lower is better).
Models with equal values share a rank (1, 1, 3) and are listed by label; a card without the value is listed last,
unranked. Each row has the value's interval and sample size, the value per category, and links to the card and,
when the card's run folder has one, to its report.html (paths relative to the leaderboard).
"""

from __future__ import annotations

import html
import json
import math
import os
import re
from pathlib import Path

from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.report.card import CARD_FILE, CARDS_DIR, KINDS, SCHEMA_NAME, CardError, estimate, read_card
from lanevil_train.rules import Rule, is_list

FILES = ("leaderboard.md", "leaderboard.json", "leaderboard.html")
REPORT_PAGE = "report.html"
LOWER_IS_BETTER = ("mCE", "relative_mCE", "ASR", "collisions")
# what must be equal for two cards to share a leaderboard, in the order differences are named
SUITE_FIELDS = ("metrics.record_kind", "metrics.primary", "suite.kind", "suite.cases", "suite.seeds",
                "suite.severities", "suite.illusions", "suite.categories")
_RANK_BY = re.compile(rf"^(?:(?:[^/]+/)?(?:{'|'.join(KINDS)})|{'|'.join(LOWER_IS_BETTER)})$")


def _cards_rule() -> Rule:
    def test(value):
        paths = [value] if isinstance(value, str) else value  # [] (the default): the task asks for cards
        if not is_list(paths) or not all(isinstance(p, str) and p for p in paths):
            return ""
        missing = [p for p in paths if not Path(p).exists()]
        return f"no such file or folder: {', '.join(missing)}" if missing else None
    return Rule("a card file or folder of cards, or a list of them ([a.json,b.json])", test)


def _rank_by_rule() -> Rule:
    return Rule(f"null, one of {', '.join(KINDS)}, <score>/<kind> (e.g. F1/Gap) or one of "
                f"{', '.join(LOWER_IS_BETTER)}",
                lambda v: None if v is None or (isinstance(v, str) and _RANK_BY.match(v)) else "")


# task=leaderboard's keys and their rules (the config check reports them by key: tasks/config_check/table.py)
SETTINGS = {"cards": _cards_rule(), "rank_by": _rank_by_rule()}


# ----------------------------------------------------------------------------------------------- the cards
def _is_card_file(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8") as handle:
            head = handle.read(4096)
    except (OSError, UnicodeDecodeError):
        return False
    return f'"{SCHEMA_NAME}"' in head


def card_paths(cards) -> list[Path]:
    """The card files named: each file as given, each folder's cards (its *.json that are cards, and every
    robustness_card.json and robustness_cards/*.json below it), each once, in order."""
    found: dict[Path, None] = {}
    for entry in [cards] if isinstance(cards, (str, Path)) else list(cards):
        path = Path(str(entry))
        if path.is_dir():
            below = sorted({*path.glob("*.json"), *path.rglob(CARD_FILE), *path.rglob(f"{CARDS_DIR}/*.json")})
            chosen = [p for p in below if _is_card_file(p)]
            if not chosen:
                raise CardError(f"task.cards: no robustness card in the folder {path} (a {CARD_FILE} or a "
                                f"{CARDS_DIR}/ of task=evaluate or task=report)")
            found.update(dict.fromkeys(chosen))
        elif path.is_file():
            found[path] = None
        else:
            raise CardError(f"task.cards: {path}: no such card file or folder")
    return list(found)


def display_names(paths: list[Path]) -> list[str]:
    """The shortest path tails that tell the cards apart (a.json; run_a/robustness_card.json)."""
    parts = [Path(os.path.abspath(p)).parts for p in paths]
    for k in range(1, max(len(p) for p in parts) + 1):
        names = ["/".join(p[-k:]) for p in parts]
        if len(set(names)) == len(names):
            return names
    return [str(p) for p in paths]


def _show(value) -> str:
    text = json.dumps(value, separators=(",", ":"))
    return text if len(text) <= 80 else text[:77] + "..."


def _field(card: dict, dotted: str):
    value = card
    for part in dotted.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def suite_differences(card: dict, first: dict) -> list[tuple[str, object, object]]:
    """(field, card's value, first's value) for each suite field where `card` differs from `first`: the fields of
    SUITE_FIELDS, the plan's settings both cards know, and the hash of the items scored when nothing else differs."""
    out = [(field, _field(card, field), _field(first, field)) for field in SUITE_FIELDS
           if _field(card, field) != _field(first, field)]
    mine, theirs = card["suite"].get("plan") or {}, first["suite"].get("plan") or {}
    out += [(f"suite.plan.{key}", mine[key], theirs[key]) for key in sorted(set(mine) & set(theirs))
            if mine[key] != theirs[key]]
    if not out and card["suite"]["plan_hash"] != first["suite"]["plan_hash"]:
        out.append(("suite.plan_hash", card["suite"]["plan_hash"], first["suite"]["plan_hash"]))
    return out


def check_same_suite(cards: list[dict], names: list[str]) -> None:
    """Raise a CardError naming every field where a card's suite differs from the first card's."""
    differences = [(name, field, value, other) for card, name in zip(cards[1:], names[1:])
                   for field, value, other in suite_differences(card, cards[0])]
    if differences:
        lines = [f"{name}: {field} {_show(value)} differs from {names[0]}'s {_show(other)}"
                 for name, field, value, other in differences]
        hint = ("\n(equal settings but other cases scored: other scenes, images or questions)"
                if all(field == "suite.plan_hash" for _, field, _, _ in differences) else "")
        raise CardError("cards of different suites cannot share a leaderboard (score every model on the same "
                        "suite plan):\n  " + "\n  ".join(lines) + hint)


# ----------------------------------------------------------------------------------------------- the ranking
def rank_key(rank_by: str | None, card: dict) -> tuple[str, bool]:
    """(the ranking key, whether higher is better) of task.rank_by for cards like `card`."""
    primary = card["metrics"]["primary"]
    key = f"{primary}/Perturbed" if rank_by is None else (f"{primary}/{rank_by}" if rank_by in KINDS else rank_by)
    if key in LOWER_IS_BETTER:
        return key, False
    score, _, kind = key.rpartition("/")
    directions = {s["name"]: s["higher_is_better"] for s in card["metrics"]["scores"]}
    if kind not in KINDS or score not in directions:
        keys = [f"{s}/{k}" for s in directions for k in KINDS]
        raise CardError(f"task.rank_by={rank_by}: the cards have no {key!r}; rank by one of "
                        f"{', '.join(keys + list(LOWER_IS_BETTER))}")
    higher = directions[score]
    return key, True if kind == "RelRobustness" else higher


def _n(card: dict, key: str) -> int | None:
    if key in ("mCE", "relative_mCE"):
        return None if card.get("mce") is None else card["mce"]["n_cases"]
    if key in ("ASR", "collisions"):
        return None if card.get("closed_loop") is None else card["closed_loop"]["overall"]["runs"]
    return card["results"]["overall"]["n_perturbed"]


def _categories(card: dict, key: str) -> list[str]:
    if key in ("mCE", "relative_mCE"):
        return list((card.get("mce") or {}).get("categories") or {}) if key == "mCE" else []
    if key in ("ASR", "collisions"):
        return list(((card.get("closed_loop") or {}).get("categories")) or {})
    return list(card["suite"]["categories"])


def _link(target: Path, out: Path) -> str:
    return Path(os.path.relpath(os.path.abspath(target), os.path.abspath(out))).as_posix()


def report_page(path: Path, card: dict) -> Path | None:
    """The report.html of the card's run: beside the card, above a robustness_cards/ folder, or in run.dir."""
    folders = [path.parent, *([path.parent.parent] if path.parent.name == CARDS_DIR else [])]
    if card["run"].get("dir"):
        folders.append(Path(card["run"]["dir"]))
    return next((folder / REPORT_PAGE for folder in folders if (folder / REPORT_PAGE).is_file()), None)


def leaderboard_rows(cards: list[dict], names: list[str], rank_by: str | None = None,
                     paths: list[Path] | None = None, out: Path | None = None) -> tuple[dict, list[dict]]:
    """({rank_by, higher_is_better, categories}, rows ranked): every card's value of the ranking key with its
    interval and sample size and its value per category; equal values share a rank (1, 1, 3); cards without a value
    come last with rank None."""
    if not cards:
        raise CardError("task.cards: no robustness card given")
    check_same_suite(cards, names)
    key, higher = rank_key(rank_by, cards[0])
    if key in ("mCE", "relative_mCE"):
        references = {(c["mce"] or {}).get("reference") for c in cards if c.get("mce")}
        if len(references) > 1:
            first = next(i for i, c in enumerate(cards) if c.get("mce"))
            other = next(i for i, c in enumerate(cards) if c.get("mce")
                         and c["mce"]["reference"] != cards[first]["mce"]["reference"])
            raise CardError(f"{names[other]}: mce.reference {cards[other]['mce']['reference']!r} differs from "
                            f"{names[first]}'s {cards[first]['mce']['reference']!r}: an mCE ranking needs one "
                            f"reference model (task=report task.baseline=...)")
    categories = list(dict.fromkeys(c for card in cards for c in _categories(card, key)))
    rows = []
    for i, (card, name) in enumerate(zip(cards, names)):
        value = estimate(card, key) or {"value": None, "low": None, "high": None}
        model = card["model"]
        row = {"rank": None, "label": model["label"], "card": name, "family": model["family"],
               "backbone": model["backbone"], "checkpoint_sha256": model["checkpoint_sha256"],
               "training_data": model["training_data"], "defense": model["defense"], **value, "n": _n(card, key),
               "categories": {c: estimate(card, key, c) for c in categories}}
        if paths is not None and out is not None:
            page = report_page(paths[i], card)
            row["card_link"] = _link(paths[i], out)
            row["report"] = None if page is None else _link(page, out)
        rows.append(row)

    def order(row):
        value = row["value"]
        missing = value is None or not math.isfinite(value)
        return missing, 0.0 if missing else (-value if higher else value), row["label"], row["card"]

    rows.sort(key=order)
    for i, row in enumerate(rows):
        if row["value"] is None:
            continue
        tied = i > 0 and rows[i - 1]["value"] == row["value"]
        row["rank"] = rows[i - 1]["rank"] if tied else i + 1
    head = {"rank_by": key, "higher_is_better": higher, "categories": categories,
            "unit": cards[0]["metrics"]["unit"]}
    return head, rows


# ----------------------------------------------------------------------------------------------- the files
def _fmt(value) -> str:
    return "—" if value is None else f"{value:.2f}"


def _cell(est: dict | None) -> str:
    if not est or est.get("value") is None:
        return "—"
    if est.get("low") is None:
        return _fmt(est["value"])
    return f"{est['value']:.2f} [{est['low']:.2f}, {est['high']:.2f}]"


def _suite_line(card: dict) -> str:
    suite = card["suite"]
    return (f"{suite['kind']} suite `{suite['dataset']}`: {suite['cases']} cases, severities "
            f"{_show(suite['severities'])}, {len(suite['illusions'])} types, plan hash {suite['plan_hash'][:19]}")


def markdown(head: dict, rows: list[dict], card: dict) -> str:
    arrow = "higher is better" if head["higher_is_better"] else "lower is better"
    columns = ["Rank", "Model", f"{head['rank_by']} [{card['metrics']['confidence']:.0%} CI]", "n",
               *head["categories"], "Report"]
    lines = ["# Leaderboard", "", f"Ranked by {head['rank_by']} ({head['unit']}, {arrow}); "
             f"{_suite_line(card)}.", "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        report = f"[report]({row['report']})" if row.get("report") else ""
        lines.append("| " + " | ".join([str(row["rank"] or "—"), row["label"], _cell(row), str(row["n"] or "—"),
                                        *(_cell(row["categories"][c]) for c in head["categories"]), report]) + " |")
    return "\n".join(lines) + "\n"


_STYLE = """body{font-family:system-ui,-apple-system,Segoe UI,sans-serif;margin:2em;color:#222}
table{border-collapse:collapse}th,td{border:1px solid #ccc;padding:.3em .6em;text-align:right}
th{background:#f2f2f2}td.model{text-align:left}tr:nth-child(even){background:#fafafa}
.ci{color:#777;font-size:.85em}.rank{font-weight:bold}small{color:#666}"""


def _html_cell(est: dict | None) -> str:
    if not est or est.get("value") is None:
        return "<td>—</td>"
    interval = (f' <span class="ci">[{est["low"]:.2f}, {est["high"]:.2f}]</span>' if est.get("low") is not None
                else "")
    return f"<td>{est['value']:.2f}{interval}</td>"


def page(head: dict, rows: list[dict], card: dict) -> str:
    """leaderboard.html: the ranked table, self-contained (inline style, no script or remote resource)."""
    esc = html.escape
    arrow = "higher is better" if head["higher_is_better"] else "lower is better"
    header = "".join(f"<th>{esc(c)}</th>" for c in ["Rank", "Model", f"{head['rank_by']} [CI]", "n",
                                                     *head["categories"], "Card", "Report"])
    body = []
    for row in rows:
        who = " ".join(x for x in (row["family"], row["backbone"]) if x)
        sha = f" · sha256 {row['checkpoint_sha256'][:12]}" if row["checkpoint_sha256"] else ""
        card_link = (f'<a href="{esc(row["card_link"])}">card</a>' if row.get("card_link") else esc(row["card"]))
        report = f'<a href="{esc(row["report"])}">report</a>' if row.get("report") else ""
        body.append(f'<tr><td class="rank">{row["rank"] or "—"}</td><td class="model">{esc(row["label"])}'
                    f"<br><small>{esc(who + sha)}</small></td>{_html_cell(row)}<td>{row['n'] or '—'}</td>"
                    + "".join(_html_cell(row["categories"][c]) for c in head["categories"])
                    + f"<td>{card_link}</td><td>{report}</td></tr>")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>Leaderboard</title>"
            f"<style>{_STYLE}</style></head><body><h1>Leaderboard</h1>"
            f"<p>Ranked by <b>{esc(head['rank_by'])}</b> ({esc(head['unit'])}, {arrow}); "
            f"{esc(_suite_line(card).replace('`', ''))}. Intervals: {esc(card['metrics']['interval'])}.</p>"
            f"<table><thead><tr>{header}</tr></thead><tbody>{''.join(body)}</tbody></table></body></html>\n")


def write_leaderboard(cards, out: str | Path, rank_by: str | None = None) -> tuple[dict[str, Path], list[dict]]:
    """Read the cards (files or folders), check they share a suite, rank them and write leaderboard.md, .json and
    .html into `out`; (the paths, the ranked rows)."""
    paths = card_paths(cards)
    names = display_names(paths)
    loaded = []
    for path, name in zip(paths, names):
        try:
            loaded.append(read_card(path))
        except CardError as error:
            raise CardError(str(error).replace(f"{path.name}: ", f"{name}: ", 1)
                            if name != path.name else str(error)) from None
    out = Path(out)
    head, rows = leaderboard_rows(loaded, names, rank_by, paths, out)
    out.mkdir(parents=True, exist_ok=True)
    first = loaded[0]
    document = {"schema_version": 1, **head, "suite": first["suite"], "metrics": first["metrics"], "rows": rows}
    written = {"md": out / FILES[0], "json": out / FILES[1], "html": out / FILES[2]}
    atomic_write_text(written["md"], markdown(head, rows, first))
    atomic_write_text(written["json"], json.dumps(document, indent=1, allow_nan=False) + "\n")
    atomic_write_text(written["html"], page(head, rows, first))
    return written, rows
