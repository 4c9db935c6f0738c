"""Question-answer pairs for a clip from the simulator's truth, in the paper's six categories (§3.6): the open
questions, the truth checks and the training-only QA.

Every reference answer is true of the real scene in every variant of the clip: the illusion is a shadow, crack,
reflection or object, never a lane marking, so the lanes, markings, weather and the safe action do not change with
it. Questions carry the illusion's cue as a camera sees it and where (qa_facts.CUES: "the dark lines in the left
lane"), never what it is; answers say what it is. A clip's 5 questions are in categories that rotate with the seed
and the segment (`clip_categories`), so the 3 clips of a case together cover all six. The closed questions (yes/no
and choice) are vlm/clips/qa_closed.py's; which are asked of which clip, so that no wording gives its answer away,
is the planner's (vlm/clips/suite_qa.py). What a QA record holds and the accuracy rule: vlm/clips/qa_records.py.
"""

from __future__ import annotations

import zlib
from types import MappingProxyType

import numpy as np

from lanevil_train.vlm.clips.qa_closed import (
    BENDS,
    CLOSED_KINDS,
    EGO_LANE_QUESTIONS,
    LANE_COUNT_QUESTIONS,
    SEGMENT_ORDER,
    blocks_ego_lane,
    boundary,
    cue,
    curve,
    distractors,
    ego_lane_words,
    is_traffic,
    lettered,
    road_shape,
    yes_no_answer,
)
from lanevil_train.vlm.clips.qa_facts import (
    ILLUSION_FACTS,
    LANE_PLACES,
    MARKING_NAMES,
    NUMBER_WORDS,
    ROAD_SHAPES,
    SCENE_KINDS_TEXT,
    WEATHER_TEXT,
    marking_text,
)
from lanevil_train.vlm.clips.qa_records import QA_CATEGORIES

REQUIRED_TRUTH = ("curvature_sign", "slope", "num_lanes", "ego_lane", "markings", "weather", "night", "wet",
                  "scene_kind", "illusion", "illusion_lane", "ego_speed_mps", "frame_step_m", "segment")


def _pick(rng: np.random.Generator, options):
    return options[int(rng.integers(len(options)))]


def _qa(category: str, question: str, answer: str) -> dict:
    return {"category": category, "type": "open", "question": question, "answer": answer}


def _is(t: dict) -> str:
    return ILLUSION_FACTS[t["illusion"]]["is"]


# ---------------------------------------------------------------------------------------------- open questions

def _weather_open(t, rng):
    q = _pick(rng, ("Describe the weather and lighting in this clip.", "What are the weather and light "
                    "conditions while the ego vehicle drives here?", "How would you describe the driving "
                    "conditions (weather, light, road surface) in these frames?"))
    surface = "wet" if t["wet"] else "dry"
    return _qa("scene_description", q, f"{WEATHER_TEXT[t['weather']]} The road surface is {surface}.")


def _road_open(t, rng):
    q = _pick(rng, ("Describe the road the ego vehicle is driving on.", "What kind of road is this, and how does "
                    "it run ahead?"))
    return _qa("scene_description", q, f"{SCENE_KINDS_TEXT[t['scene_kind']]} {ROAD_SHAPES[road_shape(t)]}")


def _illusion_identity_open(t, rng):
    seen = cue(t)
    q = _pick(rng, (f"What are the {seen}?", f"Identify the {seen}.", f"What object or effect produces the {seen}?"))
    note = ILLUSION_FACTS[t["illusion"]]["note"]
    return _qa("object_recognition", q, f"They are {_is(t)}, not lane markings. {note}")


def _lane_count_open(t, q):
    return _qa("lane_recognition", q, f"The road has {NUMBER_WORDS[t['num_lanes']]} lanes.")


def _ego_lane_open(t, q):
    return _qa("lane_recognition", q,
               f"The ego vehicle is in {ego_lane_words(t)}; the road has {NUMBER_WORDS[t['num_lanes']]} lanes.")


def _lane_count_open_kind(t, rng):
    return _lane_count_open(t, _pick(rng, LANE_COUNT_QUESTIONS))


def _ego_lane_open_kind(t, rng):
    return _ego_lane_open(t, _pick(rng, EGO_LANE_QUESTIONS))


def _boundary_marking_open(t, rng):
    side = _pick(rng, ("left", "right"))
    q = _pick(rng, (f"What marking is on the {side} side of the ego lane?",
                    f"Describe the line that bounds the ego lane on the {side}."))
    return _qa("lane_recognition", q, f"On the {side} of the ego lane there is {marking_text(boundary(t, side))}.")


_SEEN = {  # how a static illusion moves in the images, by segment (clips.py: traffic is passed, never driven over)
    False: {"before": "they are ahead of the ego vehicle and come closer, moving down the image",
            "over": "the ego vehicle drives onto them, so they slide down and out of the bottom of the image",
            "alongside": "the ego vehicle drives along them until their far end"},
    True: {"before": "they are far ahead and grow slowly in the image",
           "over": "the ego vehicle closes in on them and they grow larger in the image",
           "alongside": "the ego vehicle comes up beside them and they move to the edge of the image"},
}


def _illusion_motion_open(t, rng):
    seen = cue(t)
    q = _pick(rng, (f"How do the {seen} move in the images over the clip?",
                    f"Describe how the position of the {seen} changes from frame to frame."))
    seen_move = _SEEN[is_traffic(t)][t["segment"]]
    if is_traffic(t) and t["segment"] == "alongside" and blocks_ego_lane(t):
        seen_move = "the ego vehicle closes in on them and stops behind them, as they block its lane"
    return _qa("object_behavior", q, f"They stay in place on the road: {seen_move} as the ego vehicle moves forward.")


def _lane_lines_open(t, rng):
    q = _pick(rng, ("How do the lane lines move in the frames as the ego vehicle drives?",
                    "What happens to the ego lane's lines from frame to frame?"))
    return _qa("object_behavior", q, f"The ego vehicle stays in {ego_lane_words(t)}, so its lane lines stay on either "
               f"side of it; their dashes and marks slide down the image as it drives forward.")


def _steering_open(t, rng):
    q = _pick(rng, ("Does the ego vehicle need to steer to follow the road?", "Which way must the ego vehicle "
                    "steer to stay in its lane?"))
    sign = curve(t)
    if sign == 0:
        a = "No steering is needed: the road runs straight here, so the ego vehicle holds its wheel steady."
    else:
        a = f"It must steer gently to the {BENDS[sign + 1]}, following the road's curve."
    return _qa("motion_reasoning", q, a)


def _safe_action_open(t, rng):
    q = _pick(rng, ("What is the safe action for the ego vehicle here, and why?",
                    "How should the ego vehicle drive through this stretch of road?"))
    follow = "follow the road's curve" if curve(t) else "hold a straight course"
    seen = cue(t)
    if blocks_ego_lane(t):
        return _qa("action", q, f"It should slow down and stop behind the {seen}: they are {_is(t)} blocking "
                   f"{ego_lane_words(t)}.")
    care = "slow down and give them room" if is_traffic(t) else "ignore them when judging the lanes"
    return _qa("action", q, f"It should stay in {ego_lane_words(t)} and {follow}; the {seen} are {_is(t)}, not lane "
               f"markings, so it should {care}.")


def _lane_keep_open(t, rng):
    q = _pick(rng, ("Which lane should the ego vehicle keep, and how must it steer?",
                    "How does the ego vehicle stay in its lane here?"))
    sign = curve(t)
    steer = f"steer gently to the {BENDS[sign + 1]} with the road" if sign else "hold its wheel straight"
    return _qa("action", q, f"It keeps to {ego_lane_words(t)} and must {steer}.")


OPEN_KINDS = {
    "scene_description": (_weather_open, _road_open),
    "object_recognition": (_illusion_identity_open,),
    "lane_recognition": (_lane_count_open_kind, _ego_lane_open_kind, _boundary_marking_open),
    "object_behavior": (_illusion_motion_open, _lane_lines_open),
    "motion_reasoning": (_steering_open,),
    "action": (_safe_action_open, _lane_keep_open),
}


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


DESCRIBE_QUESTION = "Describe the scene: the setting, the lanes, the weather and light, and the road ahead."


def describe_scene(truth: dict, base_clip_id: str) -> dict:
    """A dense description of what a clip's frames show (setting, lane count and ego lane, weather, light and
    surface, road shape, the bend a slope hides and the steering it asks for) as a QA record
    `{base_clip_id}-describe`. Training-only: never one of the benchmark's QA. Every phrase is one the QA's answers
    use, so a small VLM trained from scratch (vlm/backends/embedded.py) learns to read the frames from it: the
    benchmark's QA alone let it learn their text prior instead."""
    check_truth(truth, f"truth of {base_clip_id}")
    shape, sign = road_shape(truth), curve(truth)
    bend = [ROAD_SHAPES[f"{BENDS[sign + 1]}_curve"]] if sign and shape in ("uphill", "downhill") else []
    steering = f"The ego vehicle must steer gently to the {BENDS[sign + 1]}." if sign else "No steering is needed."
    answer = " ".join((SCENE_KINDS_TEXT[truth["scene_kind"]],
                       f"The road has {NUMBER_WORDS[truth['num_lanes']]} lanes; the ego vehicle is in "
                       f"{ego_lane_words(truth)}.", WEATHER_TEXT[truth["weather"]],
                       f"The road surface is {'wet' if truth['wet'] else 'dry'}.",
                       ROAD_SHAPES[shape], *bend, steering))
    return {"qa_id": f"{base_clip_id}-describe", "base_clip_id": base_clip_id,
            **_qa("scene_description", DESCRIBE_QUESTION, answer)}


def _closed_aids(truth: dict, rng: np.random.Generator) -> list[dict]:
    """A yes/no question the clip answers Yes, one it answers No and a choice question, each of a closed kind
    drawn first (then one of its candidates), so no kind with many templates crowds out the others."""
    def answers(candidate: dict, wanted) -> bool:
        return candidate["type"] == "choice" if wanted == "choice" else candidate.get("yes") is wanted

    kinds = [(category, kind) for category, kinds in CLOSED_KINDS.items() for kind in kinds]
    out = []
    for wanted in (True, False, "choice"):
        fits = [(category, [c for c in kind(truth) if answers(c, wanted)]) for category, kind in kinds]
        fits = [(category, candidates) for category, candidates in fits if candidates]
        category, candidates = fits[int(rng.integers(len(fits)))]
        candidate = candidates[int(rng.integers(len(candidates)))]
        record = {"category": category, "type": candidate["type"], "question": candidate["template"]}
        if candidate["type"] == "yes_no":
            out.append({**record, "answer": yes_no_answer(candidate)})
            continue
        texts = [candidate["correct"], *distractors(candidate, rng)]
        texts = [texts[i] for i in rng.permutation(len(texts))]
        choices, answer = lettered(texts, candidate["correct"])
        out.append({**record, "answer": answer, "choices": choices})
    return out


def training_aids(truth: dict, base_clip_id: str) -> list[dict]:
    """A clip's training-only QA, from its truth: the scene description (`{base_clip_id}-describe`), then the open
    questions whose answers name what the frames show (`{base_clip_id}-aid1..4`): the lane count, the ego lane, the
    steering the road's bend asks for and the safe action; then closed questions of the benchmark's closed kinds
    (`-aid5..7`): one the clip answers Yes, one it answers No and a choice question. Never part of the benchmark's
    QA; phrased as the benchmark's own kinds, with the phrasing drawn from the clip id.

    Why: a small VLM trained from scratch (vlm/backends/embedded.py) gets its say on the frames from a few answer tokens
    ("three", "left"); in the 5 benchmark QA of a clip those are rare (one steering question in about 30), in a
    description one token in 60. Short answers that turn on a fact make that fact's tokens a large part of the loss
    (what that changes: benchmarks/RESULTS.md, "VLM fine-tuning"). The closed aids give each clip a Yes and a No,
    so a closed answer can only be learned from the frames."""
    check_truth(truth, f"truth of {base_clip_id}")
    rng = np.random.default_rng([zlib.crc32(base_clip_id.encode("utf-8")), 0xA1D])
    facts = (_lane_count_open(truth, _pick(rng, LANE_COUNT_QUESTIONS)),
             _ego_lane_open(truth, _pick(rng, EGO_LANE_QUESTIONS)), _steering_open(truth, rng),
             _safe_action_open(truth, rng), *_closed_aids(truth, rng))
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
             "left_marking": boundary(truth, "left"), "right_marking": boundary(truth, "right"),
             "bend": BENDS[curve(truth) + 1]}
    return [values.index(facts[name]) for name, values in SCENE_CLASSES.items()]
