"""A leakage audit for any QA file: how much of its closed questions' answers the words alone give away.

`audit(records)` splits the questions by scene into `folds` parts, fits the text-only reader
(vlm/backends/text_only.py) on all parts but one and answers that one, for each part in turn, so every question is
answered by a reader that never saw its scene. It reports, per QA type, per category and type, and per template:

- the answer shares: Yes's share of the yes/no answers; for choice questions the share of the most frequent correct
  option text and of the most frequent correct letter;
- the text-only accuracy beside chance (yes/no 50 %, a choice question 1 / its options);
- per template (its wording, `template` where the record carries one, else the question with numbers and <...>
  references masked, which groups DriveLM's object questions), whether it gives its answer away: asked at least
  `min_count` times and either its majority answer is too frequent for a balanced template (an exact binomial test:
  Yes or No against 1/2; the most frequent correct option text against 1 / options, for any of them) or the
  text-only reader answers it better than chance (binomial), each at `alpha` after a Bonferroni correction over
  the templates judged.

Read from a clip suite folder (qa.jsonl; the scenes from clips.jsonl: frames need not be there) or a DriveLM-style
QA JSON file (`read_qa_file`), or made for simulated scenes from their truth, without a frame (`synthetic_qa`).
"""

from __future__ import annotations

import re
from collections import Counter, defaultdict
from pathlib import Path
from typing import Sequence

import numpy as np

from lanevil_train.vlm.backends.text_only import TextOnlyReader, option_text
from lanevil_train.vlm.clips.qa_records import QA_CATEGORIES, answer_is_correct

CLOSED_TYPES = ("yes_no", "choice")
FOLDS = 2
MIN_COUNT = 8
ALPHA = 0.01
_MASK = re.compile(r"<[^<>]*>|\d+(?:\.\d+)?")


def template_of(qa: dict) -> str:
    """The template a question was made from: its `template` field, else its words with numbers and <...>
    references masked as #."""
    if isinstance(qa.get("template"), str) and qa["template"]:
        return qa["template"]
    return " ".join(_MASK.sub("#", qa["question"]).split())


def read_qa_file(path: str | Path) -> list[dict]:
    """The QA records of a clip suite folder (or its qa.jsonl) or a DriveLM-style QA JSON file, each with its
    "scene" (the case its base clip was rendered from; a DriveLM scene token); errors name the file and line."""
    from lanevil_train.vlm.clips.clip_set import CLIPS_FILE, QA_FILE, check_clip_record, read_lines
    from lanevil_train.vlm.clips.drivelm import read_drivelm
    from lanevil_train.vlm.clips.qa_records import check_qa_record

    path = Path(path)
    if path.is_file() and path.suffix == ".json":
        clips, qas = read_drivelm(path)
    else:
        folder = path if path.is_dir() else path.parent
        qa_file = path if path.is_file() else folder / QA_FILE
        qas = [check_qa_record(r, where) for r, where in read_lines(qa_file)]
        clips = ([check_clip_record(r, where) for r, where in read_lines(folder / CLIPS_FILE)]
                 if (folder / CLIPS_FILE).is_file() else [])
    scenes = {c["base_clip_id"]: c["case_id"] for c in clips}
    if not qas:
        raise ValueError(f"{path}: no QA to audit")
    return [{**qa, "scene": scenes.get(qa["base_clip_id"], qa["base_clip_id"])} for qa in qas]


def synthetic_qa(cases: int, first_seed: int, progress: str = "auto") -> list[dict]:
    """The QA `task=build data=clips task.cases=N` would write for N simulated scenes from `first_seed`, each with its
    "scene", from the scenes' truth alone (no frame rendered)."""
    from lanevil_train.progress import progress_counter
    from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite

    suite = SyntheticClipSuite(cases, first_seed)
    bar, qas = progress_counter(len(suite.by_base), desc="QA from the scenes' truth", unit="base clip",
                                mode=progress), []
    for base, (case, _) in suite.by_base.items():
        qas += [{**qa, "scene": case.case_id} for qa in suite.qa_for(base)]
        bar.update(1)
    bar.close()
    return qas


def _chance(qa: dict) -> float:
    return 0.5 if qa["type"] == "yes_no" else 1.0 / len(qa["choices"])


def _correct_text(qa: dict) -> str:
    letter = qa["answer"].split(".", 1)[0].strip()
    return next((option_text(c)[1] for c in qa["choices"] if option_text(c)[0] == letter), qa["answer"])


def _binomial_p(successes: int, n: int, p: float) -> float:
    """P(at least `successes` of `n`) under a rate `p`: one-sided exact binomial test."""
    from scipy.stats import binomtest

    return float(binomtest(successes, n, p, alternative="greater").pvalue) if n else 1.0


def cross_fitted_answers(records: Sequence[dict], folds: int = FOLDS, seed: int = 0) -> list[str]:
    """The text-only reader's answer to each record, fitted on the other folds' scenes (scenes dealt to folds in
    an order the seed shuffles)."""
    if not isinstance(folds, int) or isinstance(folds, bool) or folds < 2:
        raise ValueError(f"folds: expected an integer >= 2, got {folds!r}")
    scenes = sorted({str(r["scene"]) for r in records})
    if len(scenes) < folds:
        raise ValueError(f"the QA come from {len(scenes)} scene(s); splitting them by scene into {folds} folds needs "
                         f"at least {folds}")
    order = np.random.default_rng(seed).permutation(len(scenes))
    fold_of = {scenes[i]: k % folds for k, i in enumerate(order)}
    answers = [""] * len(records)
    for fold in range(folds):
        held = [i for i, r in enumerate(records) if fold_of[str(r["scene"])] == fold]
        train = [r for r in records if fold_of[str(r["scene"])] != fold]
        reader = TextOnlyReader().fit(train)
        for i in held:
            answers[i] = reader.predict(records[i])
    return answers


def _summary(records: list[dict], correct: list[bool]) -> dict:
    """n, the answer shares, the text-only accuracy and chance (%) of closed questions of one type."""
    n = len(records)
    out = {"n": n, "text_only_accuracy": 100.0 * float(np.mean(correct)),
           "chance": 100.0 * float(np.mean([_chance(r) for r in records]))}
    if records[0]["type"] == "yes_no":
        out["yes_share"] = 100.0 * float(np.mean([r["answer"].lower().startswith("yes") for r in records]))
    else:
        texts = Counter(_correct_text(r) for r in records)
        letters = Counter(r["answer"].split(".", 1)[0].strip() for r in records)
        out["top_option"], count = texts.most_common(1)[0]
        out["top_option_share"] = 100.0 * count / n
        out["top_letter"], count = letters.most_common(1)[0]
        out["top_letter_share"] = 100.0 * count / n
    return out


def _template_verdict(records: list[dict], correct: list[bool]) -> dict:
    """The template's p-values: its majority answer against a balanced template, the reader against chance."""
    n = len(records)
    if records[0]["type"] == "yes_no":
        yes = sum(r["answer"].lower().startswith("yes") for r in records)
        majority = min(1.0, 2 * _binomial_p(max(yes, n - yes), n, 0.5))  # two-sided: either answer
    else:
        options = len(records[0]["choices"])
        top = Counter(_correct_text(r) for r in records).most_common(1)[0][1]
        majority = min(1.0, options * _binomial_p(top, n, 1.0 / options))  # any of the options
    chance = float(np.mean([_chance(r) for r in records]))
    return {"p_majority": majority, "p_reader": _binomial_p(int(sum(correct)), n, chance)}


def audit(records: Sequence[dict], folds: int = FOLDS, seed: int = 0, min_count: int = MIN_COUNT,
          alpha: float = ALPHA) -> dict:
    """The audit of QA records (read_qa_file's): {"by_type", "by_category", "templates", "leaking", "settings"}
    (see the module docstring); every accuracy and share in %."""
    if not isinstance(min_count, int) or isinstance(min_count, bool) or min_count < 2:
        raise ValueError(f"min_count: expected an integer >= 2, got {min_count!r}")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha: expected a level in (0, 1), e.g. 0.01, got {alpha!r}")
    records = list(records)
    answers = cross_fitted_answers(records, folds, seed)
    closed = [(r, bool(answer_is_correct(r, a))) for r, a in zip(records, answers) if r["type"] in CLOSED_TYPES]
    if not closed:
        raise ValueError("the QA hold no yes/no or choice question: there is nothing a text-only reader could answer")
    groups: dict[tuple, list] = defaultdict(list)
    for r, ok in closed:
        groups["type", r["type"]].append((r, ok))
        groups["category", r["category"], r["type"]].append((r, ok))
        groups["template", r["type"], template_of(r)].append((r, ok))
    by_type = [{"type": key[1], **_summary(*map(list, zip(*items)))}
               for key, items in groups.items() if key[0] == "type"]
    order = {c: i for i, c in enumerate(QA_CATEGORIES)}
    by_category = sorted(({"category": key[1], "type": key[2], **_summary(*map(list, zip(*items)))}
                          for key, items in groups.items() if key[0] == "category"),
                         key=lambda row: (order.get(row["category"], len(order)), row["type"]))
    templates = []
    for key, items in groups.items():
        if key[0] != "template":
            continue
        rs, oks = map(list, zip(*items))
        row = {"type": key[1], "template": key[2], "category": Counter(r["category"] for r in rs).most_common(1)[0][0],
               **_summary(rs, oks)}
        if len(rs) >= min_count:
            row.update(_template_verdict(rs, oks))
        templates.append(row)
    judged = [t for t in templates if "p_majority" in t]
    for t in judged:
        t["leaks"] = bool(min(t["p_majority"], t["p_reader"]) * len(judged) < alpha)
    templates.sort(key=lambda t: (not t.get("leaks", False), -t["n"], t["template"]))
    return {"by_type": by_type, "by_category": by_category, "templates": templates,
            "leaking": [t for t in templates if t.get("leaks")],
            "settings": {"folds": folds, "seed": seed, "min_count": min_count, "alpha": alpha,
                         "questions": len(records), "closed": len(closed), "scenes": len({r["scene"] for r in records}),
                         "templates_judged": len(judged)}}


# ---------------------------------------------------------------------------------------------- the report

_TYPE_COLUMNS = {"yes_no": ["n", "yes_share", "text_only_accuracy", "chance"],
                 "choice": ["n", "top_option", "top_option_share", "top_letter", "top_letter_share",
                            "text_only_accuracy", "chance"]}


def audit_markdown(result: dict, source: str) -> str:
    """The audit as a markdown report: per type, per category and type, the leaking templates, the most asked."""
    from lanevil_train.report.tables import markdown_table

    s = result["settings"]
    lines = [f"# QA leakage audit: {source}", "",
             f"{s['questions']} questions ({s['closed']} yes/no or choice) of {s['scenes']} scenes. A text-only "
             f"reader (question and options, never a frame: vlm/backends/text_only.py) fitted on {s['folds'] - 1} of "
             f"{s['folds']} folds of the scenes answers the other fold's questions, for each fold in turn. A template "
             f"asked at least {s['min_count']} times leaks when its majority answer is too frequent for a balanced "
             f"template, or the reader beats chance on it (exact binomial tests, {s['alpha']} after a Bonferroni "
             f"correction over the {s['templates_judged']} templates judged). Shares and accuracies in %.", ""]
    for kind in CLOSED_TYPES:
        rows = [r for r in result["by_type"] if r["type"] == kind]
        if not rows:
            continue
        lines += [f"## {kind.replace('_', '/')} questions", "", markdown_table(rows, _TYPE_COLUMNS[kind], digits=1), "",
                  markdown_table([r for r in result["by_category"] if r["type"] == kind],
                                 ["category", *_TYPE_COLUMNS[kind]], digits=1), ""]
    leaking = result["leaking"]
    lines += [f"## Templates that give their answer away ({len(leaking)})", ""]
    if leaking:
        lines += [markdown_table(leaking, ["type", "category", "template", "n", "yes_share", "top_option",
                                           "top_option_share", "text_only_accuracy", "chance", "p_majority",
                                           "p_reader"], digits=3), ""]
    else:
        lines += ["None at this level.", ""]
    most = sorted(result["templates"], key=lambda t: -t["n"])[:20]
    lines += ["## The most asked templates", "",
              markdown_table(most, ["type", "category", "template", "n", "yes_share", "top_option_share",
                                    "text_only_accuracy", "chance", "leaks"], digits=1), ""]
    return "\n".join(lines)


def audit_plot(result: dict, path: Path) -> Path:
    """Text-only accuracy beside chance per category, one panel per closed type."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lanevil_train.report.plots import save_figure

    kinds = [k for k in CLOSED_TYPES if any(r["type"] == k for r in result["by_category"])]
    fig, axes = plt.subplots(1, len(kinds), figsize=(6 * len(kinds), 3.6), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        rows = [r for r in result["by_category"] if r["type"] == kind]
        x = np.arange(len(rows))
        ax.bar(x - 0.2, [r["text_only_accuracy"] for r in rows], 0.4, label="text-only reader")
        ax.bar(x + 0.2, [r["chance"] for r in rows], 0.4, label="chance", color="0.7")
        ax.set_xticks(x, [r["category"].replace("_", "\n") for r in rows], fontsize=8)
        ax.set_ylim(0, 100)
        ax.set_ylabel("accuracy (%)")
        ax.set_title(f"{kind.replace('_', '/')} questions")
        ax.legend(fontsize=8)
    fig.suptitle("What the words alone answer (held-out scenes)")
    return save_figure(fig, path)


def write_audit(result: dict, out: str | Path, source: str) -> dict[str, Path]:
    """qa_audit.{json,md,png} in `out`, each written whole (atomically)."""
    import json

    from lanevil_train.files.atomic import atomic_write_text

    out = Path(out)
    paths = {"json": out / "qa_audit.json", "md": out / "qa_audit.md", "png": out / "qa_audit.png"}
    atomic_write_text(paths["json"], json.dumps({"source": source, **result}, indent=1) + "\n")
    atomic_write_text(paths["md"], audit_markdown(result, source))
    audit_plot(result, paths["png"])
    return paths
