"""The closed (yes/no and choice) questions a clip can be asked, each with its answer from the scene truth.

A closed kind is a function of the truth alone that lists every question it could ask of the clip, as candidates:
a yes/no candidate {"type": "yes_no", "template", "yes", "reason"} and a choice candidate {"type": "choice",
"template", "correct", "domain"} (the option texts the question's answer can take over a suite, the correct one
among them). The template is the question's wording with the scene's values filled in, the same for every clip it
is asked of; which candidates a suite asks is the planner's (vlm/clips/suite_qa.py), which asks each template where
its answer is Yes as often as where it is No, and each choice template with its correct option text spread over
its domain, so that no wording gives its answer away.

Every kind's wording holds for any scene: the answer turns on the scene. Illusions are named by what a camera sees
and where (qa_facts.CUES: "the dark lines in the left lane" is a crack in one clip and a rail's shadow in the next),
never by what they are; the questions about them ask what they are made of, whether they stand up from the road,
whether the ego vehicle reaches them or must stop for them, so that a twin scene answers the same words the other
way. A wording no scene answers both ways ("Are the dark lines ... painted lane markings?" is No everywhere in
this simulator: no illusion is paint) is never asked closed: the open questions (vlm/clips/qa.py) ask it.
"""

from __future__ import annotations

from lanevil_train.vlm.clips.qa_facts import (
    CUE_GROUP,
    CUES,
    ILLUSION_FACTS,
    LANE_PLACES,
    MARKING_NAMES,
    NATURE,
    NATURES,
    NUMBER_WORDS,
    ORDINALS,
    ROAD_SHAPES,
    SCENE_KINDS_TEXT,
    crossing_allowed,
    marking_text,
)

SIDES = ("left", "right")
BENDS = ("left", "straight", "right")  # the road's bend over a clip, indexed by curve + 1
SEGMENT_ORDER = ("before", "over", "alongside")


def yes_no(template: str, yes: bool, reason: str) -> dict:
    return {"type": "yes_no", "template": template, "yes": bool(yes), "reason": reason}


def choice(template: str, correct: str, domain) -> dict:
    domain = tuple(dict.fromkeys(domain))
    if correct not in domain:
        raise ValueError(f"choice {template!r}: the correct option {correct!r} is not in its domain {domain}")
    return {"type": "choice", "template": template, "correct": correct, "domain": domain}


def yes_no_answer(candidate: dict) -> str:
    """A yes/no candidate's reference answer: "Yes. <reason>" or "No. <reason>"."""
    return f"{'Yes' if candidate['yes'] else 'No'}. {candidate['reason']}"


CHOICE_OPTIONS = 4  # a choice question has this many options, or its domain's size where that is smaller


def distractors(candidate: dict, rng) -> list[str]:
    """The wrong options of a choice candidate: CHOICE_OPTIONS - 1 texts of its domain other than the correct one
    (all of them when the domain is smaller), drawn without replacement in the order drawn."""
    others = [d for d in candidate["domain"] if d != candidate["correct"]]
    count = min(CHOICE_OPTIONS, len(candidate["domain"])) - 1
    return [others[i] for i in rng.choice(len(others), count, replace=False)]


def lettered(texts, correct: str) -> tuple[list[str], str]:
    """(["A. text", ...], the correct one's "X. text") of option texts in their order."""
    choices = [f"{chr(65 + k)}. {text}" for k, text in enumerate(texts)]
    return choices, choices[list(texts).index(correct)]


# ---------------------------------------------------------------------------------------------- truth, in words

def curve(truth: dict) -> int:
    """-1 the road bends left over the clip, +1 right, 0 straight (clips.clip_truth's curvature_sign)."""
    sign = truth["curvature_sign"] or 0
    return (sign > 0) - (sign < 0)


def road_shape(truth: dict) -> str:
    """The road's shape over the clip (a ROAD_SHAPES key): its slope where it climbs or falls, else its bend."""
    if truth["slope"] in ("uphill", "downhill"):
        return truth["slope"]
    return {-1: "left_curve", 0: "straight", 1: "right_curve"}[curve(truth)]


def boundary(truth: dict, side: str) -> str:
    """The marking on `side` ("left"/"right") of the ego lane."""
    return truth["markings"][truth["ego_lane"] + (0 if side == "left" else 1)]


def ego_lane_words(truth: dict) -> str:
    n, ego = truth["num_lanes"], truth["ego_lane"]
    if ego == 0:
        return "the leftmost lane"
    if ego == n - 1:
        return "the rightmost lane"
    return f"the {ORDINALS[ego]} lane from the left"


def cue(truth: dict) -> str:
    """The illusion as a camera sees it and where it lies: "dark lines in the left lane"."""
    return f"{CUES[CUE_GROUP[truth['illusion']]]} {LANE_PLACES[truth['illusion_lane']]}"


def is_traffic(truth: dict) -> bool:
    return bool(ILLUSION_FACTS[truth["illusion"]]["traffic"])


def blocks_ego_lane(truth: dict) -> bool:
    """A real road user stands in the ego lane (or across the lanes): the ego vehicle must stop behind it."""
    return is_traffic(truth) and truth["illusion_lane"] in ("ego", "across")


def reached(truth: dict) -> bool:
    """Whether the ego vehicle comes level with or drives onto the illusion within the clip (clips.py's segments:
    surface illusions are driven onto from `over` on; traffic is only come level with when passed `alongside`, and
    a road user blocking the ego lane is stopped short of)."""
    if is_traffic(truth):
        return truth["segment"] == "alongside" and not blocks_ego_lane(truth)
    return truth["segment"] != "before"


def speed_kmh(truth: dict) -> float:
    return float(truth["ego_speed_mps"]) * 3.6


def change_allowed(truth: dict, side: str) -> bool:
    """Whether the ego vehicle may change to the lane on its `side`: there is one and its line may be crossed."""
    n, ego = truth["num_lanes"], truth["ego_lane"]
    if (ego == 0) if side == "left" else (ego == n - 1):
        return False
    return crossing_allowed(boundary(truth, side), from_side="right" if side == "left" else "left")


def _is(truth: dict) -> str:
    return ILLUSION_FACTS[truth["illusion"]]["is"]


# ---------------------------------------------------------------------------------------------- scene description

NIGHT_QUESTIONS = ("Is this clip recorded at night?", "Is it night-time in this scene?",
                   "Is the ego vehicle driving in the dark?")
DAY_QUESTIONS = ("Is this clip recorded in daylight?", "Is it daytime in this scene?", "Is the scene lit by daylight?")


def light_yes_no(t):
    reason = "It is night; the road is lit only by lamps and headlights." if t["night"] else "It is daytime."
    return ([yes_no(q, t["night"], reason) for q in NIGHT_QUESTIONS] +
            [yes_no(q, not t["night"], reason) for q in DAY_QUESTIONS])


def surface_yes_no(t):
    wet = bool(t["wet"])
    reason = f"The road surface is {'wet' if wet else 'dry'}."
    return ([yes_no(q, wet, reason) for q in ("Is the road surface wet?", "Does the asphalt look wet in this clip?")] +
            [yes_no(q, not wet, reason) for q in ("Is the road dry?", "Is the asphalt dry in this clip?")])


def rain_yes_no(t):
    rain = t["weather"] == "soft_rain_noon"
    return [yes_no("Is it raining in this clip?", rain, "It is raining lightly." if rain else "It is not raining.")]


def scene_kind_choice(t):
    return [choice(q, SCENE_KINDS_TEXT[t["scene_kind"]], SCENE_KINDS_TEXT.values())
            for q in ("What kind of road environment is this?", "Where is the ego vehicle driving?",
                      "Which setting best describes this scene?")]


def road_shape_choice(t):
    return [choice(q, ROAD_SHAPES[road_shape(t)], ROAD_SHAPES.values())
            for q in ("How does the road run ahead of the ego vehicle?", "What is the shape of the road in this clip?",
                      "Which description fits the road geometry here?")]


# ---------------------------------------------------------------------------------------------- object recognition

def nature_yes_no(t):
    """What the illusion is made of, asked of each nature: light, a mark in the asphalt, a real object."""
    nature, seen = NATURE[t["illusion"]], cue(t)
    reason = f"They are {_is(t)}."
    return [yes_no(q, nature == name, reason) for name, words in NATURES.items()
            for q in (f"Are the {seen} {words}?", f"Would you call the {seen} {words}?")]


def identity_yes_no(t):
    """Whether the illusion is each of the things its cue may be."""
    group, seen = CUE_GROUP[t["illusion"]], cue(t)
    return [yes_no(f"Are the {seen} {ILLUSION_FACTS[name]['is']}?", name == t["illusion"], f"They are {_is(t)}.")
            for name in CUE_GROUP if CUE_GROUP[name] == group]


def identity_choice(t):
    group, seen = CUE_GROUP[t["illusion"]], cue(t)
    domain = [ILLUSION_FACTS[name]["is"].capitalize() + "." for name in CUE_GROUP if CUE_GROUP[name] == group]
    return [choice(q, _is(t).capitalize() + ".", domain)
            for q in (f"What are the {seen}?", f"What causes the {seen}?", f"Which of these best explains the {seen}?")]


# ---------------------------------------------------------------------------------------------- lane recognition

LANE_COUNT_QUESTIONS = ("How many lanes does this road have?", "How many driving lanes can you count on the road?",
                        "Count the lanes of the road in this clip.")
EGO_LANE_QUESTIONS = ("Which lane is the ego vehicle driving in?", "In which lane is the camera car?",
                      "Counting from the left, which lane does the ego vehicle occupy?")
LANE_COUNTS = (2, 3, 4, 5)
EGO_LANE_CHOICES = 4  # the ego lane's choice question names the first four lanes


def lane_count_choice(t):
    domain = [f"{NUMBER_WORDS[k].capitalize()} lanes." for k in LANE_COUNTS]
    return [choice(q, domain[LANE_COUNTS.index(t["num_lanes"])], domain) for q in LANE_COUNT_QUESTIONS]


def lane_count_yes_no(t):
    n = t["num_lanes"]
    return [yes_no(f"Does this road have {NUMBER_WORDS[k]} lanes?", k == n, f"The road has {NUMBER_WORDS[n]} lanes.")
            for k in LANE_COUNTS]


def ego_lane_choice(t):
    if t["ego_lane"] >= EGO_LANE_CHOICES:
        return []
    domain = [f"The {ORDINALS[k]} lane from the left." for k in range(EGO_LANE_CHOICES)]
    return [choice(q, domain[t["ego_lane"]], domain) for q in EGO_LANE_QUESTIONS]


def ego_lane_yes_no(t):
    n, ego, reason = t["num_lanes"], t["ego_lane"], f"The ego vehicle is in {ego_lane_words(t)}."
    return [yes_no("Is the ego vehicle in the leftmost lane?", ego == 0, reason),
            yes_no("Is the ego vehicle in the rightmost lane?", ego == n - 1, reason),
            *(yes_no(f"Is the ego vehicle in the {ORDINALS[k]} lane from the left?", ego == k, reason)
              for k in range(1, 4))]


def boundary_yes_no(t):
    out = []
    for side in SIDES:
        marking = boundary(t, side)
        reason = f"On the {side} of the ego lane there is {marking_text(marking)}."
        painted = marking != "none"
        out.append(yes_no(f"Is there a painted line on the {side} of the ego lane?", painted, reason))
        for colour in ("white", "yellow"):
            out.append(yes_no(f"Is the line on the {side} of the ego lane {colour}?",
                              painted and marking.startswith(colour), reason))
        out += [yes_no(f"Is the ego lane marked on its {side} by {marking_text(m)}?", m == marking, reason)
                for m in MARKING_NAMES]
    return out


# ---------------------------------------------------------------------------------------------- object behaviour

def reach_yes_no(t):
    seen, now = cue(t), reached(t)
    if now:
        reason = "It drives onto them." if not is_traffic(t) else "It comes up beside them."
    else:
        reason = ("It stops short of them: they block its lane." if blocks_ego_lane(t)
                  else "They are still ahead of it at the end of the clip.")
    return [yes_no(f"Does the ego vehicle reach the {seen} during this clip?", now, reason),
            yes_no(f"Are the {seen} still ahead of the ego vehicle at the end of the clip?", not now, reason)]


def upright_yes_no(t):
    seen, stands = cue(t), NATURE[t["illusion"]] == "object"
    reason = f"They are {_is(t)}" + (", which stand up from the road." if stands else ", flat on the road surface.")
    return [yes_no(f"Do the {seen} stand up above the road surface?", stands, reason),
            yes_no(f"Do the {seen} lie flat on the road surface?", not stands, reason)]


# ---------------------------------------------------------------------------------------------- motion reasoning

SPEED_LIMITS_KMH = (40, 50)


def speed_yes_no(t):
    kmh = speed_kmh(t)
    reason = f"It moves about {float(t['frame_step_m']):.0f} m between frames, about {kmh:.0f} km/h."
    return [yes_no(f"Is the ego vehicle driving faster than {v} km/h?", kmh > v, reason) for v in SPEED_LIMITS_KMH]


def steer_yes_no(t):
    sign = curve(t)
    reason = (f"The road bends to the {BENDS[sign + 1]}, so it steers gently that way." if sign else
              "The road runs straight; no steering is needed.")
    return [*(yes_no(f"Must the ego vehicle steer to the {side} to stay in its lane?", sign == (-1 if side == "left"
                                                                                                 else 1), reason)
              for side in SIDES),
            yes_no("Can the ego vehicle hold its wheel straight to stay in its lane?", sign == 0, reason)]


APPROACHES = ("Approaching them from a distance.", "Closing in on them, a few metres away.", "Driving over them.",
              "Passing beside them.", "Stopping behind them.")


def approach_choice(t):
    """Where the ego vehicle is relative to the illusion (clips.py's segments): surface illusions are approached,
    driven over and passed; road users approached, closed in on and passed, or stopped behind when they block."""
    seen, segment = cue(t), t["segment"]
    if is_traffic(t):
        correct = {"before": 0, "over": 1, "alongside": 4 if blocks_ego_lane(t) else 3}[segment]
    else:
        correct = {"before": 0, "over": 2, "alongside": 3}[segment]
    return [choice(q, APPROACHES[correct], APPROACHES)
            for q in (f"Relative to the {seen}, what is the ego vehicle doing?",
                      f"Where is the ego vehicle relative to the {seen} in this clip?")]


# ---------------------------------------------------------------------------------------------- action

NEXT_ACTIONS = ("Keep driving straight on in its lane.", "Follow the road's bend to the left in its lane.",
                "Follow the road's bend to the right in its lane.", "Slow down and stop behind what blocks its lane.")


def safe_action(t) -> str:
    """The safe action (a NEXT_ACTIONS text): stop behind a road user in its lane, else follow the road."""
    return NEXT_ACTIONS[3] if blocks_ego_lane(t) else NEXT_ACTIONS[{0: 0, -1: 1, 1: 2}[curve(t)]]


def next_action_choice(t):
    return [choice(q, safe_action(t), NEXT_ACTIONS)
            for q in ("What should the ego vehicle do next?", "Which action is the safe one for the ego vehicle?")]


def stop_yes_no(t):
    seen, stop = cue(t), blocks_ego_lane(t)
    reason = (f"They are {_is(t)} in its way; it must slow down and stop." if stop else
              f"They are {_is(t)}, not in its way; it keeps following the real lane lines.")
    return [yes_no(f"Must the ego vehicle stop before the {seen}?", stop, reason),
            yes_no(f"Can the ego vehicle keep driving in its lane past the {seen}?", not stop, reason)]


def lane_change_yes_no(t):
    out = []
    for side in SIDES:
        allowed = change_allowed(t, side)
        if (t["ego_lane"] == 0) if side == "left" else (t["ego_lane"] == t["num_lanes"] - 1):
            reason = f"The ego vehicle is already in {ego_lane_words(t)}; there is no lane on its {side}."
        else:
            rule = "may be crossed when the lane is clear" if allowed else "must not be crossed"
            reason = f"The line on its {side} is {marking_text(boundary(t, side))}, which {rule}."
        out.append(yes_no(f"May the ego vehicle change to the lane on its {side} here?", allowed, reason))
    return out


CLOSED_KINDS = {
    "scene_description": (light_yes_no, surface_yes_no, rain_yes_no, scene_kind_choice, road_shape_choice),
    "object_recognition": (nature_yes_no, identity_yes_no, identity_choice),
    "lane_recognition": (lane_count_choice, lane_count_yes_no, ego_lane_choice, ego_lane_yes_no, boundary_yes_no),
    "object_behavior": (reach_yes_no, upright_yes_no),
    "motion_reasoning": (speed_yes_no, steer_yes_no, approach_choice),
    "action": (next_action_choice, stop_yes_no, lane_change_yes_no),
}
