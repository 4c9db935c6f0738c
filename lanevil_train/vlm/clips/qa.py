"""Question-answer pairs for a clip from the simulator's truth, in the paper's six categories (§3.6).

`make_qa(truth, base_clip_id, seed)` writes 5 QA for one base (clean) clip. Every reference answer is true of
the real scene in every variant of the clip: the illusion is a shadow, crack, reflection or object, never a lane
marking, so the lanes, markings, weather and the safe action do not change with it. Questions carry the
illusion's cue (what it looks like and where), as the paper asks: "Is the dark straight line in the left lane a
lane marking?" -> "No. It is the shadow of a rail ...". Categories rotate with the seed and the segment, so the
3 clips of a case together cover all six; each category has several question kinds and each kind several
phrasings. The benchmark pays no answer prior: `case_plan` draws each yes/no question's true answer so that a
case's Yes and No are even (per category and overall, to within one) and each yes/no kind phrases its question
so the truth answers it that way ("Is it daytime?" / "Is it night?"); every choice question has CHOICE_OPTIONS
options with the correct letter dealt evenly. What a QA record holds and the accuracy rule: vlm/clips/qa_records.py.
"""

from __future__ import annotations

import zlib
from functools import lru_cache
from types import MappingProxyType

import numpy as np

from lanevil_train.vlm.clips.qa_facts import (
    ILLUSION_FACTS,
    LANE_PLACES,
    MARKING_NAMES,
    NUMBER_WORDS,
    ORDINALS,
    ROAD_SHAPES,
    SCENE_KIND_DISTRACTOR,
    SCENE_KINDS_TEXT,
    SPEED_BANDS,
    WEATHER_TEXT,
    crossing_allowed,
    marking_text,
)
from lanevil_train.vlm.clips.qa_records import QA_CATEGORIES

SEGMENT_ORDER = ("before", "over", "alongside")
REQUIRED_TRUTH = ("curvature_sign", "slope", "num_lanes", "ego_lane", "markings", "weather", "night", "wet",
                  "scene_kind", "illusion", "illusion_lane", "ego_speed_mps", "frame_step_m", "segment")


# ---------------------------------------------------------------------------------------------- helpers

CHOICE_OPTIONS = 4  # every choice question has this many options; the correct one's letter is uniform over them


def _pick(rng: np.random.Generator, options):
    return options[int(rng.integers(len(options)))]


def _choice_qa(category: str, question: str, correct: str, distractors, rng: np.random.Generator,
               letter: int | None = None) -> dict:
    """A choice QA of CHOICE_OPTIONS options, the correct one and distractors drawn from `distractors`, shuffled
    with the rng so that the correct letter is uniform over A.. and no answer prior pays; the correct one goes
    to index `letter` when the case plan gives one."""
    pool = [d for d in dict.fromkeys(distractors) if d != correct]
    if len(pool) < CHOICE_OPTIONS - 1:
        raise ValueError(f"{category} choice {question!r}: expected {CHOICE_OPTIONS - 1} distractors, got {pool}")
    options = [correct, *(pool[i] for i in rng.choice(len(pool), CHOICE_OPTIONS - 1, replace=False))]
    order = [int(i) for i in rng.permutation(CHOICE_OPTIONS)]
    if letter is not None:
        order.remove(0)
        order.insert(letter, 0)
    choices = [f"{chr(65 + k)}. {options[i]}" for k, i in enumerate(order)]
    return {"category": category, "type": "choice", "question": question,
            "answer": choices[order.index(0)], "choices": choices}


def _qa(category: str, kind: str, question: str, answer: str) -> dict:
    return {"category": category, "type": kind, "question": question, "answer": answer}


def _yes_wanted(rng: np.random.Generator) -> bool:
    """A fair coin for the true answer of a yes/no question; the kind then phrases the question so that the
    truth answers it that way, which balances a suite's yes and no answers."""
    return bool(rng.random() < 0.5)


def _yes_no(category: str, question: str, yes: bool, reason: str) -> dict:
    return _qa(category, "yes_no", question, f"{'Yes' if yes else 'No'}. {reason}")


def _cue(truth: dict) -> tuple[dict, str]:
    """The illusion's facts and where it lies, as words ("in the left lane")."""
    return ILLUSION_FACTS[truth["illusion"]], LANE_PLACES[truth["illusion_lane"]]


def _other_identity(truth: dict, rng: np.random.Generator) -> str:
    """What another illusion type really is (a false identity for the clip's illusion)."""
    own = ILLUSION_FACTS[truth["illusion"]]["is"]
    return _pick(rng, [f["is"] for f in ILLUSION_FACTS.values() if f["is"] != own])


def _ego_lane_words(truth: dict) -> str:
    n, ego = truth["num_lanes"], truth["ego_lane"]
    if ego == 0:
        return "the leftmost lane"
    if ego == n - 1:
        return "the rightmost lane"
    return f"the {ORDINALS[ego]} lane from the left"


BENDS = ("left", "straight", "right")  # the road's bend over a clip, indexed by _curve + 1


def _curve(truth: dict) -> int:
    """-1 the road bends left over the clip, +1 right, 0 straight (clips.clip_truth's curvature_sign)."""
    return int(np.sign(truth["curvature_sign"] or 0))


def road_shape(truth: dict) -> str:
    """The road's shape over the clip (a ROAD_SHAPES key): its slope where it climbs or falls, else its bend."""
    if truth["slope"] in ("uphill", "downhill"):
        return truth["slope"]
    return {-1: "left_curve", 0: "straight", 1: "right_curve"}[_curve(truth)]


def _boundary(truth: dict, side: str) -> str:
    """The marking on `side` ("left"/"right") of the ego lane."""
    return truth["markings"][truth["ego_lane"] + (0 if side == "left" else 1)]


# ---------------------------------------------------------------------------------------------- scene description

def _weather_open(t, rng):
    q = _pick(rng, ("Describe the weather and lighting in this clip.", "What are the weather and light "
                    "conditions while the ego vehicle drives here?", "How would you describe the driving "
                    "conditions (weather, light, road surface) in these frames?"))
    surface = "wet" if t["wet"] else "dry"
    return _qa("scene_description", "open", q, f"{WEATHER_TEXT[t['weather']]} The road surface is {surface}.")


def _night_yes_no(t, rng, yes=None):
    yes = _yes_wanted(rng) if yes is None else yes
    q = _pick(rng, ("Is this clip recorded at night?", "Is it night-time in this scene?",
                    "Is the ego vehicle driving in the dark?") if yes == t["night"] else
              ("Is this clip recorded in daylight?", "Is it daytime in this scene?",
               "Is the scene lit by daylight?"))
    a = "It is night; the road is lit only by lamps and headlights." if t["night"] else "It is daytime."
    return _yes_no("scene_description", q, yes, a)


def _wet_yes_no(t, rng, yes=None):
    yes, wet = _yes_wanted(rng) if yes is None else yes, bool(t["wet"])
    q = _pick(rng, ("Is the road surface wet?", "Does the asphalt look wet in this clip?") if yes == wet else
              ("Is the road dry?", "Is the asphalt dry in this clip?"))
    return _yes_no("scene_description", q, yes, f"The road surface is {'wet' if wet else 'dry'}.")


def _scene_kind_choice(t, rng, letter=None):
    q = _pick(rng, ("What kind of road environment is this?", "Where is the ego vehicle driving?",
                    "Which setting best describes this scene?"))
    return _choice_qa("scene_description", q, SCENE_KINDS_TEXT[t["scene_kind"]],
                      [*SCENE_KINDS_TEXT.values(), SCENE_KIND_DISTRACTOR], rng, letter)


def _road_shape_choice(t, rng, letter=None):
    q = _pick(rng, ("How does the road run ahead of the ego vehicle?", "What is the shape of the road in this "
                    "clip?", "Which description fits the road geometry here?"))
    return _choice_qa("scene_description", q, ROAD_SHAPES[road_shape(t)], list(ROAD_SHAPES.values()), rng, letter)


# ---------------------------------------------------------------------------------------------- object recognition

def _illusion_identity_choice(t, rng, letter=None):
    facts, place = _cue(t)
    q = _pick(rng, (f"What are the {facts['looks']} {place}?", f"What causes the {facts['looks']} {place}?",
                    f"Which of these best explains the {facts['looks']} {place}?"))
    others = [f["is"].capitalize() + "." for f in ILLUSION_FACTS.values() if f["is"] != facts["is"]]
    options = [others[i] for i in rng.choice(len(others), CHOICE_OPTIONS - 2, replace=False)]
    return _choice_qa("object_recognition", q, facts["is"].capitalize() + ".",
                      ["Lane markings painted on the road.", *options], rng, letter)


def _illusion_identity_open(t, rng):
    facts, place = _cue(t)
    q = _pick(rng, (f"What are the {facts['looks']} {place}?", f"Identify the {facts['looks']} {place}.",
                    f"What object or effect produces the {facts['looks']} {place}?"))
    return _qa("object_recognition", "open", q, f"They are {facts['is']}, not lane markings. {facts['note']}")


def _illusion_is_object_yes_no(t, rng, yes=None):
    facts, place = _cue(t)
    yes = _yes_wanted(rng) if yes is None else yes
    if yes:
        q = _pick(rng, (f"Are the {facts['looks']} {place} {facts['is']}?",
                        f"Are the {facts['looks']} {place} {facts['is']} rather than lane markings?"))
    else:
        q = _pick(rng, (f"Are the {facts['looks']} {place} painted road markings?",
                        f"Are the {facts['looks']} {place} part of the lane markings?",
                        f"Are the {facts['looks']} {place} {_other_identity(t, rng)}?"))
    return _yes_no("object_recognition", q, yes, f"They are {facts['is']}; the lane markings are unchanged.")


# ---------------------------------------------------------------------------------------------- lane recognition

LANE_COUNT_QUESTIONS = ("How many lanes does this road have?", "How many driving lanes can you count on the road?",
                        "Count the lanes of the road in this clip.")
EGO_LANE_QUESTIONS = ("Which lane is the ego vehicle driving in?", "In which lane is the camera car?",
                      "Counting from the left, which lane does the ego vehicle occupy?")


def _lane_count(t, rng, letter=None):
    n = t["num_lanes"]
    q = _pick(rng, LANE_COUNT_QUESTIONS)
    if rng.random() < 0.5:
        return _choice_qa("lane_recognition", q, f"{NUMBER_WORDS[n].capitalize()} lanes.",
                          [f"{NUMBER_WORDS[k].capitalize()} lanes." for k in range(2, 6)], rng, letter)
    return _lane_count_open(t, q)


def _lane_count_open(t, q):
    return _qa("lane_recognition", "open", q, f"The road has {NUMBER_WORDS[t['num_lanes']]} lanes.")


def _ego_lane(t, rng, letter=None):
    n, ego = t["num_lanes"], t["ego_lane"]
    q = _pick(rng, EGO_LANE_QUESTIONS)
    if rng.random() < 0.5:
        lanes = [f"The {ORDINALS[k]} lane from the left." for k in range(max(n, CHOICE_OPTIONS))]
        return _choice_qa("lane_recognition", q, lanes[ego], lanes, rng, letter)
    return _ego_lane_open(t, q)


def _ego_lane_open(t, q):
    return _qa("lane_recognition", "open", q,
               f"The ego vehicle is in {_ego_lane_words(t)}; the road has {NUMBER_WORDS[t['num_lanes']]} lanes.")


def _boundary_marking_open(t, rng):
    side = _pick(rng, ("left", "right"))
    q = _pick(rng, (f"What marking is on the {side} side of the ego lane?",
                    f"Describe the line that bounds the ego lane on the {side}."))
    return _qa("lane_recognition", "open", q,
               f"On the {side} of the ego lane there is {marking_text(_boundary(t, side))}.")


MARKING_QUESTIONS_NO = ("a lane marking?", "mark a lane boundary?", "be read as a lane line?")


def _marking_vs_illusion_yes_no(t, rng, yes=None):
    facts, place = _cue(t)
    one, lanes = facts["looks_one"], NUMBER_WORDS[t["num_lanes"]]
    yes = _yes_wanted(rng) if yes is None else yes
    if yes:
        q = _pick(rng, (f"Is the {one} {place} really {facts['is_one']}?",
                        f"Should the {one} {place} be ignored when counting the lanes?",
                        f"Does the road still have {lanes} lanes despite the {one} {place}?"))
    else:
        q = _pick(rng, (f"Is the {one} {place} {MARKING_QUESTIONS_NO[0]}",
                        f"Does the {one} {place} {MARKING_QUESTIONS_NO[1]}",
                        f"Should the {one} {place} {MARKING_QUESTIONS_NO[2]}"))
    return _yes_no("lane_recognition", q, yes, f"It is {facts['is_one']}, not a lane marking; the road still has "
                   f"{lanes} lanes.")


def _boundary_color_yes_no(t, rng, yes=None):
    yes, side = _yes_wanted(rng) if yes is None else yes, _pick(rng, ("left", "right"))
    marking = _boundary(t, side)
    if marking == "none":
        q = (f"Does the ego lane end at the bare road edge on its {side}?" if yes else
             f"Is there a painted line on the {side} of the ego lane?")
        return _yes_no("lane_recognition", q, yes, f"There is no painted line on the {side} of the ego lane; "
                       f"the lane ends at the road edge.")
    if rng.random() < 0.5:
        actual = "yellow" if marking.startswith("yellow") else "white"
        colour = actual if yes else {"yellow": "white", "white": "yellow"}[actual]
        q = _pick(rng, (f"Is the line on the {side} of the ego lane {colour}?",
                        f"Is the ego lane bounded on the {side} by a {colour} line?"))
    else:
        asked = marking if yes else _pick(rng, [m for m in MARKING_NAMES if m != marking])
        q = f"Is the ego lane marked on its {side} by {marking_text(asked)}?"
    return _yes_no("lane_recognition", q, yes, f"It is {marking_text(marking)}.")


# ---------------------------------------------------------------------------------------------- object behaviour

def _illusion_static_yes_no(t, rng, yes=None):
    facts, place = _cue(t)
    yes = _yes_wanted(rng) if yes is None else yes
    q = _pick(rng, (f"Do the {facts['looks']} {place} stay in place on the road as the ego vehicle drives on?",
                    f"Are the {facts['looks']} {place} standing still on the road?") if yes else
              (f"Do the {facts['looks']} {place} move along with the traffic?",
               f"Are the {facts['looks']} {place} moving?"))
    return _yes_no("object_behavior", q, yes, f"They are {facts['is']}, which stay in place on the road while the "
                   f"ego vehicle drives past.")


def _illusion_motion_open(t, rng):
    facts, place = _cue(t)
    q = _pick(rng, (f"How do the {facts['looks']} {place} move in the images over the clip?",
                    f"Describe how the position of the {facts['looks']} {place} changes from frame to frame."))
    return _qa("object_behavior", "open", q, f"They stay in place on the road: {_SEEN[facts['traffic']][t['segment']]} "
               f"as the ego vehicle moves forward.")


_SEEN = {  # how a static illusion moves in the images, by segment (clips.py: traffic is passed, never driven over)
    False: {"before": "they are ahead of the ego vehicle and come closer, moving down the image",
            "over": "the ego vehicle drives onto them, so they slide down and out of the bottom of the image",
            "alongside": "the ego vehicle drives along them until their far end"},
    True: {"before": "they are far ahead and grow slowly in the image",
           "over": "the ego vehicle closes in on them and they grow larger in the image",
           "alongside": "the ego vehicle comes up beside them and they move to the edge of the image"},
}


def _markings_shift_yes_no(t, rng, yes=None):
    yes = _yes_wanted(rng) if yes is None else yes
    q = _pick(rng, ("Does the ego vehicle stay between the same two lane lines throughout the clip?",
                    "Do the ego lane's lines stay on either side of the ego vehicle during the clip?") if yes else
              ("Do the lane markings shift sideways relative to the ego vehicle during the clip?",
               "Does the ego vehicle drift across a lane line in this clip?"))
    return _yes_no("object_behavior", q, yes, f"The ego vehicle stays in {_ego_lane_words(t)}, so its lane lines "
                   f"stay on either side of it.")


# ---------------------------------------------------------------------------------------------- motion reasoning

def _speed_kmh(t) -> float:
    return float(t["ego_speed_mps"]) * 3.6


def _moving_yes_no(t, rng, yes=None):
    yes, moving = _yes_wanted(rng) if yes is None else yes, t["ego_speed_mps"] > 0.1
    q = _pick(rng, ("Is the ego vehicle moving forward in this clip?", "Is the ego vehicle driving forward?")
              if yes == moving else ("Is the ego vehicle standing still?", "Is the ego vehicle stopped in this clip?"))
    detail = (f"It moves forward about {float(t['frame_step_m']):.0f} m between frames, about "
              f"{_speed_kmh(t):.0f} km/h.") if moving else "It is stopped."
    return _yes_no("motion_reasoning", q, yes, detail)


def _speed_choice(t, rng, letter=None):
    q = _pick(rng, ("About how fast is the ego vehicle driving?", "Which speed range fits the ego vehicle?"))
    kmh = _speed_kmh(t)
    band = 0 if kmh < 1 else 1 if kmh < 20 else 2 if kmh < 40 else 3 if kmh <= 60 else 4
    return _choice_qa("motion_reasoning", q, SPEED_BANDS[band], SPEED_BANDS, rng, letter)


def _approach_choice(t, rng, letter=None):
    facts, place = _cue(t)
    q = _pick(rng, (f"Relative to the {facts['looks']} {place}, what is the ego vehicle doing?",
                    f"Where is the ego vehicle relative to the {facts['looks']} {place} in this clip?"))
    options = (["Approaching them from a distance.", "Closing in on them, a few metres away.",
                "Passing right beside them."] if facts["traffic"] else
               ["Approaching them from a distance.", "Driving over them.", "Passing alongside them."])
    return _choice_qa("motion_reasoning", q, options[SEGMENT_ORDER.index(t["segment"])],
                      [*options, "Moving away from them; they are behind it."], rng, letter)


def _steering_open(t, rng):
    q = _pick(rng, ("Does the ego vehicle need to steer to follow the road?", "Which way must the ego vehicle "
                    "steer to stay in its lane?"))
    sign = _curve(t)
    if sign == 0:
        a = "No steering is needed: the road runs straight here, so the ego vehicle holds its wheel steady."
    else:
        a = f"It must steer gently to the {BENDS[sign + 1]}, following the road's curve."
    return _qa("motion_reasoning", "open", q, a)


# ---------------------------------------------------------------------------------------------- action

def _swerve_yes_no(t, rng, yes=None):
    facts, place = _cue(t)
    yes, looks = _yes_wanted(rng) if yes is None else yes, f"{facts['looks']} {place}"
    if facts["traffic"]:
        q = (f"Should the ego vehicle keep to its lane and give the {looks} room?" if yes else
             f"Should the ego vehicle treat the {looks} as lane lines and steer between them?")
        a = f"They are {facts['is']}, not lane lines; it should keep to its lane, slow down and give them room."
    else:
        q = _pick(rng, (f"Should the ego vehicle keep following the real lane lines past the {looks}?",
                        f"Can the ego vehicle keep its path past the {looks}?") if yes else
                  (f"Should the ego vehicle steer away from the {looks}?",
                   f"Should the ego vehicle change its path because of the {looks}?"))
        a = f"They are {facts['is']}, not lane markings; it should keep following the real lane lines."
    return _yes_no("action", q, yes, a)


def _next_action_choice(t, rng, letter=None):
    facts, _ = _cue(t)
    q = _pick(rng, ("What should the ego vehicle do next?", "Which action is the safe one for the ego vehicle?"))
    keep = ("Keep its lane at reduced speed, ready to stop for the people or vehicles near the lane line."
            if facts["traffic"] else "Keep driving in its lane, following the road.")
    return _choice_qa("action", q, keep, ["Brake hard to a full stop.", "Swerve into the lane on its left.",
                                          "Swerve into the lane on its right."], rng, letter)


def _safe_action_open(t, rng):
    facts, place = _cue(t)
    q = _pick(rng, ("What is the safe action for the ego vehicle here, and why?",
                    "How should the ego vehicle drive through this stretch of road?"))
    sign = _curve(t)
    follow = "follow the road's curve" if sign else "hold a straight course"
    care = "slow down and give them room" if facts["traffic"] else "ignore them when judging the lanes"
    return _qa("action", "open", q, f"It should stay in {_ego_lane_words(t)} and {follow}; the {facts['looks']} "
               f"{place} are {facts['is']}, not lane markings, so it should {care}.")


def _change_allowed(t, side: str) -> bool:
    """Whether the ego vehicle may change to the lane on its `side`: there is one and its line may be crossed."""
    n, ego = t["num_lanes"], t["ego_lane"]
    if (ego == 0) if side == "left" else (ego == n - 1):
        return False
    return crossing_allowed(_boundary(t, side), from_side="right" if side == "left" else "left")


def _lane_change_yes_no(t, rng, yes=None):
    want = _yes_wanted(rng) if yes is None else yes  # a wish: the truth may allow only one answer
    sides = [s for s in ("left", "right") if _change_allowed(t, s) == want] or ["left", "right"]
    side = _pick(rng, sides)
    q = f"May the ego vehicle change to the lane on its {side} here?"
    allowed = _change_allowed(t, side)
    if (t["ego_lane"] == 0) if side == "left" else (t["ego_lane"] == t["num_lanes"] - 1):
        return _yes_no("action", q, False, f"The ego vehicle is already in {_ego_lane_words(t)}; there is no "
                       f"lane on its {side}.")
    marking = _boundary(t, side)
    rule = "may be crossed when the lane is clear" if allowed else "must not be crossed"
    return _yes_no("action", q, allowed, f"The line on its {side} is {marking_text(marking)}, which {rule}.")


KINDS = {
    "scene_description": (_weather_open, _night_yes_no, _wet_yes_no, _scene_kind_choice, _road_shape_choice),
    "object_recognition": (_illusion_identity_choice, _illusion_identity_open, _illusion_is_object_yes_no),
    "lane_recognition": (_lane_count, _ego_lane, _boundary_marking_open, _marking_vs_illusion_yes_no,
                         _boundary_color_yes_no),
    "object_behavior": (_illusion_static_yes_no, _illusion_motion_open, _markings_shift_yes_no),
    "motion_reasoning": (_moving_yes_no, _speed_choice, _approach_choice, _steering_open),
    "action": (_swerve_yes_no, _next_action_choice, _safe_action_open, _lane_change_yes_no),
}
CHOICE_KINDS = frozenset((_scene_kind_choice, _road_shape_choice, _illusion_identity_choice, _lane_count, _ego_lane,
                          _speed_choice, _approach_choice, _next_action_choice))  # may be choice: take `letter`
YES_NO_KINDS = frozenset((_night_yes_no, _wet_yes_no, _illusion_is_object_yes_no, _marking_vs_illusion_yes_no,
                          _boundary_color_yes_no, _illusion_static_yes_no, _markings_shift_yes_no, _moving_yes_no,
                          _swerve_yes_no, _lane_change_yes_no))  # these take the wanted answer as `yes`


# ---------------------------------------------------------------------------------------------- public

def check_truth(truth: dict, where: str = "truth") -> None:
    """The truth has every key the templates read, with values they know; else a ValueError naming the key."""
    if not isinstance(truth, dict):
        raise ValueError(f"{where}: expected a dict of scene truth, got {type(truth).__name__}")
    missing = [k for k in REQUIRED_TRUTH if k not in truth]
    if missing:
        raise ValueError(f"{where}: missing keys {', '.join(missing)} (clips.clip_truth gives them)")
    n = truth["num_lanes"]
    checks = [("illusion", truth["illusion"] in ILLUSION_FACTS, f"one of {', '.join(ILLUSION_FACTS)}"),
              ("illusion_lane", truth["illusion_lane"] in LANE_PLACES, f"one of {', '.join(LANE_PLACES)}"),
              ("num_lanes", isinstance(n, int) and 2 <= n <= 5, "an integer from 2 to 5"),
              ("ego_lane", isinstance(truth["ego_lane"], int) and 0 <= truth["ego_lane"] < (n if isinstance(n, int)
                                                                                          else 0),
               "an integer from 0 to num_lanes - 1"),
              ("markings", isinstance(truth["markings"], (list, tuple)) and len(truth["markings"]) == n + 1
               if isinstance(n, int) else False, "num_lanes + 1 marking names"),
              ("slope", truth["slope"] in ("flat", "uphill", "downhill"), "one of flat, uphill, downhill"),
              ("curvature_sign", truth["curvature_sign"] in (-1, 0, 1), "-1 (left), 0 or 1 (right)"),
              ("weather", truth["weather"] in WEATHER_TEXT, f"one of {', '.join(WEATHER_TEXT)}"),
              ("scene_kind", truth["scene_kind"] in SCENE_KINDS_TEXT, f"one of {', '.join(SCENE_KINDS_TEXT)}"),
              ("segment", truth["segment"] in SEGMENT_ORDER, f"one of {', '.join(SEGMENT_ORDER)}")]
    for key, good, expected in checks:
        if not good:
            raise ValueError(f"{where}: {key}: expected {expected}, got {truth[key]!r}")


def clip_categories(seed: int, segment: str, per_clip: int) -> list[str]:
    """The categories of one clip's QA: a rotation started by the seed and shifted by the segment, so the 3
    segments of a case leave out 3 different categories and together cover all six."""
    start = int(np.random.default_rng([seed, 0x9A]).integers(len(QA_CATEGORIES))) + SEGMENT_ORDER.index(segment)
    return [QA_CATEGORIES[(start + k) % len(QA_CATEGORIES)] for k in range(per_clip)]


@lru_cache(maxsize=4096)
def case_plan(seed: int, per_clip: int) -> dict[str, tuple[tuple[str, int, bool | int | None], ...]]:
    """The QA slots of a case's 3 clips, segment -> ((category, kind index, wanted answer), ...), from the seed
    alone so the clips are planned together. Wanted answer: for yes/no kinds, a category's questions in a case
    come in Yes/No pairs (in coin order) and the unpaired ones alternate across categories, so a case's yes/no
    answers are even to within one, per category and overall; for choice kinds, the correct option's index,
    dealt from shuffled decks of the CHOICE_OPTIONS letters, so every letter is equally often right; else None."""
    rng = np.random.default_rng([int(seed), 0x59E5])
    slots: dict[str, list[list]] = {}
    for segment in SEGMENT_ORDER:
        used: dict[str, list[int]] = {}
        slots[segment] = []
        for category in clip_categories(int(seed), segment, per_clip):
            free = [i for i in range(len(KINDS[category])) if i not in used.get(category, [])]
            kind = _pick(rng, free or list(range(len(KINDS[category]))))
            used.setdefault(category, []).append(kind)
            slots[segment].append([category, kind, None])
    yes_no: dict[str, list[list]] = {}
    letters: list[int] = []
    for slot in (slot for segment in SEGMENT_ORDER for slot in slots[segment]):
        if KINDS[slot[0]][slot[1]] in YES_NO_KINDS:
            yes_no.setdefault(slot[0], []).append(slot)
        elif KINDS[slot[0]][slot[1]] in CHOICE_KINDS:
            letters = letters or [int(i) for i in rng.permutation(CHOICE_OPTIONS)]
            slot[2] = letters.pop()
    odd_one = _yes_wanted(rng)
    for category in QA_CATEGORIES:
        questions = yes_no.get(category, [])
        for k in range(0, len(questions) - 1, 2):
            first = _yes_wanted(rng)
            questions[k][2], questions[k + 1][2] = first, not first
        if len(questions) % 2:
            questions[-1][2], odd_one = odd_one, not odd_one
    return {segment: tuple(tuple(slot) for slot in slots[segment]) for segment in SEGMENT_ORDER}


def make_qa(truth: dict, base_clip_id: str, seed: int, per_clip: int = 5) -> list[dict]:
    """`per_clip` QA for the base clip `base_clip_id` from its scene truth; deterministic given the seed. The
    kinds and the wanted yes/no answers come from `case_plan(seed)`, the phrasings and options from the seed
    and the clip id."""
    check_truth(truth, f"truth of {base_clip_id}")
    if not isinstance(per_clip, int) or per_clip < 1:
        raise ValueError(f"per_clip: expected an integer >= 1, got {per_clip!r}")
    rng = np.random.default_rng([int(seed), zlib.crc32(base_clip_id.encode("utf-8"))])
    out = []
    for k, (category, index, yes) in enumerate(case_plan(int(seed), per_clip)[truth["segment"]]):
        kind = KINDS[category][index]
        qa = kind(truth, rng) if yes is None else kind(truth, rng, yes)
        out.append({"qa_id": f"{base_clip_id}-q{k}", "base_clip_id": base_clip_id, **qa})
    return out


DESCRIBE_QUESTION = "Describe the scene: the setting, the lanes, the weather and light, and the road ahead."


def describe_scene(truth: dict, base_clip_id: str) -> dict:
    """A dense description of what a clip's frames show (setting, lane count and ego lane, weather, light and
    surface, road shape, the bend a slope hides and the steering it asks for) as a QA record
    `{base_clip_id}-describe`. Training-only: never one of the benchmark's QA. Every phrase is one the QA's answers
    use, so a small VLM trained from scratch (vlm/backends/embedded.py) learns to read the frames from it: the
    benchmark's QA alone let it learn their text prior instead."""
    check_truth(truth, f"truth of {base_clip_id}")
    shape, sign = road_shape(truth), _curve(truth)
    bend = [ROAD_SHAPES[f"{BENDS[sign + 1]}_curve"]] if sign and shape in ("uphill", "downhill") else []
    steering = f"The ego vehicle must steer gently to the {BENDS[sign + 1]}." if sign else "No steering is needed."
    answer = " ".join((SCENE_KINDS_TEXT[truth["scene_kind"]],
                       f"The road has {NUMBER_WORDS[truth['num_lanes']]} lanes; the ego vehicle is in "
                       f"{_ego_lane_words(truth)}.", WEATHER_TEXT[truth["weather"]],
                       f"The road surface is {'wet' if truth['wet'] else 'dry'}.",
                       ROAD_SHAPES[shape], *bend, steering))
    return {"qa_id": f"{base_clip_id}-describe", "base_clip_id": base_clip_id,
            **_qa("scene_description", "open", DESCRIBE_QUESTION, answer)}


def training_aids(truth: dict, base_clip_id: str) -> list[dict]:
    """A clip's training-only QA, from its truth: the scene description (`{base_clip_id}-describe`), then the open
    questions whose answers name what the frames show (`{base_clip_id}-aid1..4`): the lane count, the ego lane, the
    steering the road's bend asks for and the safe action. Never part of the benchmark's QA; phrased as the
    benchmark's own open kinds, with the phrasing drawn from the clip id.

    Why: a small VLM trained from scratch (vlm/backends/embedded.py) gets its say on the frames from a few answer tokens
    ("three", "left"); in the 5 benchmark QA of a clip those are rare (one steering question in about 30), in a
    description one token in 60. Short answers that turn on a fact make that fact's tokens a large part of the loss
    (what that changes: benchmarks/RESULTS.md, "VLM fine-tuning")."""
    check_truth(truth, f"truth of {base_clip_id}")
    rng = np.random.default_rng([zlib.crc32(base_clip_id.encode("utf-8")), 0xA1D])
    facts = (_lane_count_open(truth, _pick(rng, LANE_COUNT_QUESTIONS)),
             _ego_lane_open(truth, _pick(rng, EGO_LANE_QUESTIONS)), _steering_open(truth, rng),
             _safe_action_open(truth, rng))
    return [describe_scene(truth, base_clip_id),
            *({"qa_id": f"{base_clip_id}-aid{k}", "base_clip_id": base_clip_id, **qa} for k, qa in enumerate(facts, 1))]


# What the embedded VLM's vision tower is pretrained to tell from a clip (embedded.pretrain_vision): each fact of
# the scene truth that its frames show, with the values it can take, in class order.
# The bend is its own fact: road_shape names the slope where there is one, and the steering and safe-action answers
# follow the bend on hills too.
SCENE_CLASSES = MappingProxyType({
    "num_lanes": (2, 3, 4, 5), "ego_lane": (0, 1, 2, 3, 4), "road_shape": tuple(ROAD_SHAPES),
    "weather": tuple(WEATHER_TEXT), "scene_kind": tuple(SCENE_KINDS_TEXT), "wet": (False, True),
    "left_marking": (*MARKING_NAMES, "none"), "right_marking": (*MARKING_NAMES, "none"), "bend": BENDS,
})


UNKNOWN_CLASS = -100  # a fact a clip does not tell (cross-entropy's ignore index)


def mirror_scene_classes(classes) -> list[int]:
    """The SCENE_CLASSES of the clip's left-right mirror image: the ego lane counted from the other side, left and
    right bends and curves swapped, the ego lane's two markings swapped; a solid-and-dashed pair mirrors into a
    dashed-and-solid one, which no marking name describes, so it becomes UNKNOWN_CLASS."""
    names, values = list(SCENE_CLASSES), list(classes)
    if len(values) != len(names) or not all(isinstance(v, (int, np.integer)) and 0 <= v < len(SCENE_CLASSES[n])
                                            for n, v in zip(names, values)):
        raise ValueError(f"classes: expected {len(names)} class indices in SCENE_CLASSES order, got {classes!r}")
    fact = {name: SCENE_CLASSES[name][int(v)] for name, v in zip(names, values)}
    if fact["ego_lane"] >= fact["num_lanes"]:
        raise ValueError(f"classes: ego lane {fact['ego_lane']} on a road of {fact['num_lanes']} lanes; expected an "
                         f"ego lane index below the lane count")
    swap = {"left": "right", "right": "left", "left_curve": "right_curve", "right_curve": "left_curve"}
    fact["ego_lane"] = fact["num_lanes"] - 1 - fact["ego_lane"]
    fact["road_shape"], fact["bend"] = swap.get(fact["road_shape"], fact["road_shape"]), swap.get(fact["bend"],
                                                                                                  fact["bend"])
    fact["left_marking"], fact["right_marking"] = fact["right_marking"], fact["left_marking"]
    return [UNKNOWN_CLASS if name.endswith("_marking") and fact[name].endswith("solid_dashed")
            else SCENE_CLASSES[name].index(fact[name]) for name in names]


def scene_classes(truth: dict, base_clip_id: str = "truth") -> list[int]:
    """The class index of each SCENE_CLASSES fact of a clip's truth, in SCENE_CLASSES order."""
    check_truth(truth, f"truth of {base_clip_id}")
    facts = {"num_lanes": truth["num_lanes"], "ego_lane": truth["ego_lane"], "road_shape": road_shape(truth),
             "weather": truth["weather"], "scene_kind": truth["scene_kind"], "wet": bool(truth["wet"]),
             "left_marking": _boundary(truth, "left"), "right_marking": _boundary(truth, "right"),
             "bend": BENDS[_curve(truth) + 1]}
    return [values.index(facts[name]) for name, values in SCENE_CLASSES.items()]
