"""The QA of a whole suite, planned together so that no question's wording gives its answer away.

`suite_qa(clips, per_clip, kind)` takes every base clip of a suite with its scene truth, in suite order, and gives
each its `per_clip` QA. Slot k of a clip is in category qa.clip_categories(seed, segment)[k]; it is open with the
chance OPEN_SHARE (drawn from the seed and the clip id), else closed. A closed slot asks one of the candidates its
category's closed kinds list for the clip (vlm/clips/qa_closed.py), of a template the suite answers more than one
way, and one the suite's balance allows:

- a yes/no template (its wording with the scene's values filled in) is asked only where that keeps its Yes and No
  counts within one of each other, and one owed the clip's answer is preferred; once every clip is planned, the
  last question of each template left one answer over becomes an open question of its category, so every yes/no
  template of a suite is asked as often where its answer is Yes as where it is No: only the frames tell them apart;
- a choice template is asked only where its correct option text stays within SHARE_SLACK of an even share of its
  domain (the texts its answer takes over a suite); its options are the correct one and others of that domain
  (all of them when the domain has at most qa_closed.CHOICE_OPTIONS), so no option is one a reader can rule out, and the
  correct letter is dealt from shuffled decks, so every letter is equally often right.

A slot no candidate fits becomes open. Records carry their `template` (vlm/answer_scoring/leakage.py audits by it). In a
corruption suite, which draws no illusion and changes how weather and light look, the kinds that read those facts
of the truth are not asked, and a slot whose category has no open kind left is dropped (the others keep their qa_id
numbers). Which facts a kind reads is found by running it on a probe truth that logs the keys read
(`template_reads`), so no list of kind names has to be kept in step.
"""

from __future__ import annotations

import zlib
from collections import defaultdict
from collections.abc import Sequence
from functools import cache

import numpy as np

from lanevil_train.perturbations import check_kind
from lanevil_train.vlm.clips.qa import OPEN_KINDS, check_truth, clip_categories
from lanevil_train.vlm.clips.qa_closed import CLOSED_KINDS, distractors, lettered, yes_no_answer

# truth keys a corruption-suite question must not read: the illusion is not drawn, weather and light are what the
# weather and brightness corruptions change the look of
CORRUPTION_UNSAFE_FACTS = frozenset(("illusion", "illusion_lane", "weather", "wet", "night"))
SHARE_SLACK = 0.05  # a choice template's correct option text stays within this of 1 / its domain's size
QA_PLAN = 2  # the QA construction a suite's build.json names: 2, planned per suite (1, before it: per case)
OPEN_SHARE = 0.3  # the chance that a slot asks an open question (else a closed one, where one fits)


def _probe_truth(illusion: str) -> dict:
    """A valid scene truth for probing which facts a QA kind reads."""
    return {"curvature_sign": -1, "slope": "flat", "num_lanes": 3, "ego_lane": 1, "weather": "clear_noon",
            "markings": ["yellow_double_solid", "white_dashed", "white_dashed", "white_solid"], "night": False,
            "wet": 0.0, "scene_kind": "urban", "illusion": illusion, "illusion_lane": "left", "ego_speed_mps": 10.0,
            "frame_step_m": 4.0, "segment": "over"}


class _ReadLog(dict):
    """A dict that notes every key read from it."""

    def __init__(self, *args) -> None:
        super().__init__(*args)
        self.read: set = set()

    def __getitem__(self, key):
        self.read.add(key)
        return super().__getitem__(key)

    def get(self, key, default=None):
        self.read.add(key)
        return super().get(key, default)


@cache
def template_reads(kind) -> frozenset:
    """The truth keys a QA kind (a closed kind of qa_closed.CLOSED_KINDS or an open one of qa.OPEN_KINDS) reads,
    probed with a traffic and a surface illusion and several draws."""
    read: set = set()
    for illusion in ("rail_shadow", "vehicle"):
        for draw in range(4):
            truth = _ReadLog(_probe_truth(illusion))
            if kind in {k for kinds in CLOSED_KINDS.values() for k in kinds}:
                kind(truth)
            else:
                kind(truth, np.random.default_rng(draw))
            read |= truth.read
    return frozenset(read)


def allowed_kinds(kinds, kind: str) -> tuple:
    """The QA kinds of `kinds` a `kind` suite asks: all, or in a corruption suite those reading none of
    CORRUPTION_UNSAFE_FACTS."""
    if check_kind(kind) != "corruptions":
        return tuple(kinds)
    return tuple(k for k in kinds if not template_reads(k) & CORRUPTION_UNSAFE_FACTS)


def kept_questions(kind: str, seed: int, segment: str, per_clip: int) -> tuple[int, ...]:
    """Which of a base clip's `per_clip` QA slots a `kind` suite asks (indices): all of them, or in a corruption
    suite those whose category keeps an open kind (from the seed alone: no truth needed)."""
    return tuple(k for k, category in enumerate(clip_categories(int(seed), segment, per_clip))
                 if allowed_kinds(OPEN_KINDS[category], kind))


class _Balance:
    """The suite's running answer counts per template, and the decks the correct letters are dealt from."""

    def __init__(self) -> None:
        self.yes_minus_no: dict[str, int] = defaultdict(int)
        self.correct: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
        self.asked: dict[str, int] = defaultdict(int)
        self.letters: dict[int, list[int]] = defaultdict(list)
        self.deck_rng = np.random.default_rng(0x1E77E5)

    def allows(self, candidate: dict) -> bool:
        template = candidate["template"]
        if candidate["type"] == "yes_no":
            return abs(self.yes_minus_no[template] + (1 if candidate["yes"] else -1)) <= 1
        share = 1.0 / len(candidate["domain"]) + SHARE_SLACK
        return self.correct[template][candidate["correct"]] <= share * (self.asked[template] + 1)

    def owed(self, candidate: dict) -> bool:
        """Asking it evens its template's answers (yes/no) or brings up its least right option (choice)."""
        template = candidate["template"]
        if candidate["type"] == "yes_no":
            return self.yes_minus_no[template] == (-1 if candidate["yes"] else 1)
        counts = self.correct[template]
        return bool(self.asked[template]) and counts[candidate["correct"]] == min(counts[d] for d in
                                                                                  candidate["domain"])

    def ask(self, candidate: dict, category: str, rng: np.random.Generator) -> dict:
        template = candidate["template"]
        self.asked[template] += 1
        record = {"category": category, "type": candidate["type"], "question": template, "template": template}
        if candidate["type"] == "yes_no":
            self.yes_minus_no[template] += 1 if candidate["yes"] else -1
            return {**record, "answer": yes_no_answer(candidate)}
        self.correct[template][candidate["correct"]] += 1
        texts = distractors(candidate, rng)
        count = len(texts) + 1
        deck = self.letters[count]
        if not deck:
            deck.extend(int(i) for i in self.deck_rng.permutation(count))
        texts.insert(deck.pop(), candidate["correct"])
        choices, answer = lettered(texts, candidate["correct"])
        return {**record, "answer": answer, "choices": choices}

    def unbalanced(self) -> set[str]:
        return {template for template, d in self.yes_minus_no.items() if d}


def _open(category: str, truth: dict, rng: np.random.Generator, kind: str) -> dict:
    kinds = allowed_kinds(OPEN_KINDS[category], kind)
    qa = kinds[int(rng.integers(len(kinds)))](truth, rng)
    return {**qa, "template": qa["question"]}


def _answer(candidate: dict):
    return candidate["yes"] if candidate["type"] == "yes_no" else candidate["correct"]


def _closed_candidates(clips, kind: str) -> list[dict[str, list[dict]]]:
    """Per clip, {category: the candidates of its closed kinds a `kind` suite asks}: computed once, read twice."""
    return [{category: [c for closed_kind in allowed_kinds(kinds, kind) for c in closed_kind(truth)]
             for category, kinds in CLOSED_KINDS.items()} for _, _, truth in clips]


def _answers_seen(candidates: list[dict[str, list[dict]]]) -> dict[str, set]:
    """The answers each closed template takes over the suite's clips (True/False, or correct option texts)."""
    seen: dict[str, set] = defaultdict(set)
    for of_clip in candidates:
        for listed in of_clip.values():
            for candidate in listed:
                seen[candidate["template"]].add(_answer(candidate))
    return seen


def _varying(candidates: list[dict], answers: dict[str, set]) -> list[dict]:
    """The candidates whose template the suite answers more than one way, a choice's domain cut to the correct texts
    the suite holds (an option never right over the suite would be one to rule out)."""
    out = []
    for candidate in candidates:
        seen = answers[candidate["template"]]
        if len(seen) < 2:
            continue
        if candidate["type"] == "choice":
            candidate = {**candidate, "domain": tuple(d for d in candidate["domain"] if d in seen)}
        out.append(candidate)
    return out


def suite_qa(clips: Sequence[tuple[str, int, dict]], per_clip: int = 5, kind: str = "illusions") -> dict[str, list]:
    """{base clip id: its QA records} for the base clips `clips`, (base clip id, case seed, scene truth) each, in
    suite order (the module docstring); deterministic given them."""
    if isinstance(per_clip, bool) or not isinstance(per_clip, int) or per_clip < 1:
        raise ValueError(f"per_clip: expected an integer >= 1, got {per_clip!r}")
    for base, _, truth in clips:
        check_truth(truth, f"truth of {base}")
    candidates = _closed_candidates(clips, kind)
    answers = _answers_seen(candidates)
    balance, out, slots = _Balance(), {}, []
    for (base, seed, truth), of_clip in zip(clips, candidates):
        rng = np.random.default_rng([int(seed), zlib.crc32(base.encode("utf-8"))])
        asked: set[str] = set()
        out[base] = []
        kept = kept_questions(kind, seed, truth["segment"], per_clip)
        for k, category in enumerate(clip_categories(int(seed), truth["segment"], per_clip)):
            if k not in kept:
                continue
            qa = None
            if of_clip[category] and rng.random() >= OPEN_SHARE:
                fits = [c for c in _varying(of_clip[category], answers)
                        if c["template"] not in asked and balance.allows(c)]
                types = sorted({c["type"] for c in fits})
                if types:
                    chosen = types[int(rng.integers(len(types)))]
                    of_type = [c for c in fits if c["type"] == chosen]
                    pool = [c for c in of_type if balance.owed(c)] or of_type
                    qa = balance.ask(pool[int(rng.integers(len(pool)))], category, rng)
            qa = qa or _open(category, truth, rng, kind)
            asked.add(qa["template"])
            out[base].append({"qa_id": f"{base}-q{k}", "base_clip_id": base, **qa})
            slots.append((base, len(out[base]) - 1, truth, rng))
    left_over = balance.unbalanced()
    for base, index, truth, rng in reversed(slots):
        qa = out[base][index]
        if qa["type"] == "yes_no" and qa["template"] in left_over:
            left_over.discard(qa["template"])
            out[base][index] = {"qa_id": qa["qa_id"], "base_clip_id": base, **_open(qa["category"], truth, rng, kind)}
    return out
