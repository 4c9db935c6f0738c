"""QA from the simulator's truth: categories, reference answers true to the scene, the accuracy rule."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lanevil_train.vlm.clips import qa as qa_module
from lanevil_train.vlm.clips.qa import clip_categories, make_qa
from lanevil_train.vlm.clips.qa_records import QA_CATEGORIES, answer_is_correct, chosen_letter
from tests.vlm.truth_fixture import truth

SEGMENTS = ("before", "over", "alongside")


def all_kinds(t: dict, seeds=range(40)) -> list[dict]:
    """Every question kind's output over many rng draws (phrasings and options vary with the rng)."""
    out = []
    for kinds in qa_module.KINDS.values():
        for kind, seed in itertools.product(kinds, seeds):
            out.append(kind(t, np.random.default_rng(seed)))
    return out


def test_five_qa_per_clip_and_one_case_covers_all_six_categories():
    suite = [qa for seg in SEGMENTS for qa in make_qa(truth(segment=seg), f"case-{seg}", seed=7)]
    assert len(suite) == 15
    assert {qa["category"] for qa in suite} == set(QA_CATEGORIES)
    for seg in SEGMENTS:
        clip = [qa for qa in suite if qa["base_clip_id"] == f"case-{seg}"]
        assert len({qa["category"] for qa in clip}) == 5
        assert [qa["qa_id"] for qa in clip] == [f"case-{seg}-q{k}" for k in range(5)]
    missing = [set(QA_CATEGORIES) - set(clip_categories(7, seg, 5)) for seg in SEGMENTS]
    assert len(set().union(*missing)) == 3  # each segment leaves out a different category


def test_deterministic_given_seed_and_different_for_another_seed():
    t = truth()
    assert make_qa(t, "c", 3) == make_qa(dict(t), "c", 3)
    assert any(make_qa(t, "c", s) != make_qa(t, "c", 3) for s in range(4, 10))


def test_categories_are_not_one_fixed_sentence():
    questions = {c: set() for c in QA_CATEGORIES}
    for seed, seg in itertools.product(range(30), SEGMENTS):
        for qa in make_qa(truth(segment=seg), "c", seed):
            questions[qa["category"]].add(qa["question"])
    assert all(len(q) >= 4 for q in questions.values()), {c: len(q) for c, q in questions.items()}


@pytest.mark.parametrize("lanes", [2, 3, 4, 5])
def test_lane_count_is_the_renderers_lane_count(lanes):
    t = truth(num_lanes=lanes, ego_lane=0, markings=["yellow_solid"] + ["white_dashed"] * (lanes - 1) +
              ["white_solid"])
    words = {2: "two", 3: "three", 4: "four", 5: "five"}
    counts = [qa for qa in all_kinds(t) if qa["question"].startswith(("How many", "Count the"))]
    assert {qa["type"] for qa in counts} == {"open", "choice"}
    for qa in counts:
        assert words[lanes] in qa["answer"].lower()
        if qa["type"] == "choice":
            assert answer_is_correct(qa, f"{words[lanes].capitalize()} lanes.")
            assert not answer_is_correct(qa, f"{words[2 + (lanes - 1) % 4].capitalize()} lanes.")


def test_marking_versus_shadow_question_is_answered_by_the_illusion():
    for illusion, lane, looks, real in (("rail_shadow", "left", "dark straight line in the left lane", "rail"),
                                        ("road_crack", "ego", "dark jagged line in the ego lane", "crack")):
        qas = [qa for qa in all_kinds(truth(illusion=illusion, illusion_lane=lane))
               if qa["category"] == "lane_recognition" and looks in qa["question"]]
        assert qas and all(qa["type"] == "yes_no" and real in qa["answer"] for qa in qas)
        asks_marking = [qa for qa in qas if qa["question"].endswith(qa_module.MARKING_QUESTIONS_NO)]
        assert asks_marking and all(qa["answer"].startswith("No.") for qa in asks_marking)
        others = [qa for qa in qas if qa not in asks_marking]  # "... really the shadow of ...?", "... ignored ...?"
        assert others and all(qa["answer"].startswith("Yes.") for qa in others)
    paper = [qa for qa in all_kinds(truth()) if qa["question"] ==
             "Is the dark straight line in the left lane a lane marking?"]
    assert paper and paper[0]["answer"].startswith("No. It is the shadow of a rail")


def test_answers_follow_the_truth():
    night = [qa for qa in all_kinds(truth(weather="night", night=True)) if qa["question"] ==
             "Is this clip recorded at night?"]
    day = [qa for qa in all_kinds(truth()) if qa["question"] == "Is this clip recorded at night?"]
    assert night[0]["answer"].startswith("Yes") and day[0]["answer"].startswith("No")
    ego = [qa for qa in all_kinds(truth(ego_lane=2)) if "lane is the ego vehicle driving in" in qa["question"]]
    assert all("rightmost" in qa["answer"] or "third lane" in qa["answer"] for qa in ego)
    # left of ego lane 1 is white_dashed (crossable); ego lane 0's left is the road's left edge
    change = [qa for qa in all_kinds(truth())
              if qa["question"] == "May the ego vehicle change to the lane on its left here?"]
    assert change[0]["answer"].startswith("Yes") and "dashed white" in change[0]["answer"]
    solid = truth(markings=["yellow_solid", "white_solid", "white_dashed", "white_solid"])
    change = [qa for qa in all_kinds(solid)
              if qa["question"] == "May the ego vehicle change to the lane on its left here?"]
    assert change[0]["answer"].startswith("No")
    shapes = [qa for qa in all_kinds(truth(slope="uphill", curvature_sign=0)) if qa["category"] == "scene_description"
              and qa["type"] == "choice" and "uphill" in " ".join(qa["choices"])]
    assert all(qa["answer"].endswith("Climbing uphill.") for qa in shapes)


def test_every_answer_has_its_form():
    for qa in all_kinds(truth(), seeds=range(5)) + all_kinds(truth(illusion="pedestrian"), seeds=range(5)):
        assert qa["answer"].endswith(".") and qa["answer"][0].isupper()
        if qa["type"] == "yes_no":
            assert qa["answer"].split(".")[0] in ("Yes", "No")
        if qa["type"] == "choice":
            assert qa["answer"] in qa["choices"]
            assert [c[0] for c in qa["choices"]] == [chr(65 + i) for i in range(len(qa["choices"]))]
        else:
            assert "choices" not in qa


def test_accuracy_rule():
    yes_no = {"type": "yes_no", "answer": "No. It is a shadow."}
    assert answer_is_correct(yes_no, "no, that is a shadow") is True
    assert answer_is_correct(yes_no, "  NO!") is True
    assert answer_is_correct(yes_no, "Yes. It is a lane line.") is False
    assert answer_is_correct(yes_no, "") is False
    choice = {"type": "choice", "answer": "B. Two lanes.", "choices": ["A. One lane.", "B. Two lanes.", "C. Three."]}
    for said in ("B", "b.", "(B) Two lanes", "Answer: B", "The answer is B.", "two lanes", "B. Two lanes."):
        assert chosen_letter(choice, said) == "B", said
        assert answer_is_correct(choice, said) is True
    for said in ("A", "A two lane road", "C. Three.", "D", "I am not sure"):
        assert answer_is_correct(choice, said) is False, said
    assert answer_is_correct({"type": "open", "answer": "It is day."}, "It is day.") is None


def test_bad_truth_is_named():
    with pytest.raises(ValueError, match="truth of c: missing keys num_lanes"):
        make_qa({k: v for k, v in truth().items() if k != "num_lanes"}, "c", 0)
    with pytest.raises(ValueError, match="illusion_lane: expected one of ego, left"):
        make_qa(truth(illusion_lane="middle"), "c", 0)
    with pytest.raises(ValueError, match="markings: expected num_lanes \\+ 1"):
        make_qa(truth(markings=["white_solid"]), "c", 0)
    with pytest.raises(ValueError, match="per_clip"):
        make_qa(truth(), "c", 0, per_clip=0)


def test_traffic_is_passed_not_driven_over_and_the_road_shape_is_the_clips():
    for seg, expected in (("over", "Closing in on them"), ("alongside", "Passing right beside them")):
        qas = [qa for qa in all_kinds(truth(illusion="vehicle", illusion_lane="ego", segment=seg))
               if qa["category"] == "motion_reasoning" and qa["type"] == "choice" and "Relative to" in qa["question"]]
        assert qas and all(qa["answer"][3:].startswith(expected) for qa in qas)
    # an s-curve scene whose clip bends right, on the level: the clip's shape, not the scene's road kind
    shapes = [qa for qa in all_kinds(truth(road="s_curve", curvature_sign=1)) if qa["category"] ==
              "scene_description" and qa["type"] == "choice" and "Going downhill." in " ".join(qa["choices"])]
    assert shapes and all(qa["answer"].endswith("Curving to the right.") for qa in shapes)


# ---------------------------------------------------------------------------------------------- fairness on a suite

@pytest.fixture(scope="module")
def suite_qa():
    """(truth, QA) of every base clip of the 28-case suite with all 14 illusions (truths only: no frames)."""
    from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite
    from lanevil_train.vlm.clips.clips import clip_truth

    suite = SyntheticClipSuite(28, 1000000, "all", (3,), (72, 128))
    out = []
    for base in sorted(suite.by_base):
        case, segment = suite.by_base[base]
        out.append((clip_truth(case, segment, size=suite.size), suite.qa_for(base)))
    return out


def test_yes_no_answers_are_balanced_over_the_suite_and_per_category(suite_qa):
    answers = {c: [] for c in QA_CATEGORIES}
    for _, qas in suite_qa:
        for qa in qas:
            if qa["type"] == "yes_no":
                answers[qa["category"]].append(qa["answer"].split(".")[0])
    every = [a for said in answers.values() for a in said]
    assert len(every) >= 150
    assert 0.45 <= every.count("Yes") / len(every) <= 0.55  # the old generator: 36 of 195 (18 %)
    for category, said in answers.items():
        if len(said) >= 20:
            share = said.count("Yes") / len(said)
            assert 0.35 <= share <= 0.65, (category, said.count("Yes"), len(said))


def test_choice_letters_are_uniform_and_every_choice_has_four_options(suite_qa):
    choices = [qa for _, qas in suite_qa for qa in qas if qa["type"] == "choice"]
    assert len(choices) >= 100 and {len(qa["choices"]) for qa in choices} == {qa_module.CHOICE_OPTIONS}
    letters = [qa["answer"][0] for qa in choices]
    for letter in "ABCD":  # the old generator: A 44 %, B 15 %, and a stray E
        assert 0.2 <= letters.count(letter) / len(letters) <= 0.3, (letter, letters.count(letter), len(letters))


def _yes(qa: dict) -> bool:
    return qa["answer"].startswith("Yes.")


def _check_against_truth(t: dict, qa: dict) -> bool | None:
    """Whether a QA whose truth a test can read agrees with the clip truth `t`; None for other questions."""
    q, n = qa["question"], t["num_lanes"]
    words = ("two", "three", "four", "five")
    if q.startswith(("How many", "Count the")):
        said = [w for w in words if w in qa["answer"].lower()]
        return said == [words[n - 2]]
    if q in ("Is this clip recorded at night?", "Is it night-time in this scene?", "Is the ego vehicle driving in "
             "the dark?"):
        return _yes(qa) == t["night"]
    if q in ("Is this clip recorded in daylight?", "Is it daytime in this scene?", "Is the scene lit by daylight?"):
        return _yes(qa) != t["night"]
    if "lane is the ego vehicle driving in" in q or "lane is the camera car" in q or "lane does the ego" in q:
        ordinal = ("first", "second", "third", "fourth", "fifth")[t["ego_lane"]]
        edge = {0: "leftmost", n - 1: "rightmost"}.get(t["ego_lane"], ordinal)
        return f"{ordinal} lane" in qa["answer"] or edge in qa["answer"]
    for side in ("left", "right"):
        marking = t["markings"][t["ego_lane"] + (side == "right")]
        if q.startswith(f"Is the ego lane marked on its {side} by "):
            asked = q[len(f"Is the ego lane marked on its {side} by "):-1]
            return _yes(qa) == (asked == qa_module.marking_text(marking))
        for colour in ("yellow", "white"):
            if q in (f"Is the line on the {side} of the ego lane {colour}?",
                     f"Is the ego lane bounded on the {side} by a {colour} line?"):
                return marking != "none" and _yes(qa) == (t["marking_colors"][t["ego_lane"] + (side == "right")]
                                                          == colour)
    return None


def test_reference_answers_match_the_renderers_truth(suite_qa):
    checked = {}
    for t, qas in suite_qa:
        for qa in qas:
            verdict = _check_against_truth(t, qa)
            if verdict is not None:
                assert verdict, (t["case_id"], t["segment"], qa)
                checked[qa["question"].split()[0]] = checked.get(qa["question"].split()[0], 0) + 1
    assert sum(checked.values()) >= 30, checked


@pytest.mark.parametrize("night", [False, True])
def test_every_yes_no_kind_says_both_yes_and_no_and_stays_true(night):
    t = truth(weather="night" if night else "clear_noon", night=night)
    for kind in qa_module.YES_NO_KINDS:
        if kind is qa_module._lane_change_yes_no:  # its answer is the markings', the wish only picks the side
            continue
        said = {kind(t, np.random.default_rng(s), yes)["answer"].split(".")[0]: yes for s in range(8)
                for yes in (False, True)}
        assert said == {"Yes": True, "No": False}, kind.__name__
    assert _check_against_truth(t, {"question": "Is it daytime in this scene?", "answer": "No. It is night."}) \
        is night


def test_case_plan_pairs_yes_and_no_and_deals_letters_evenly():
    for seed in range(40):
        plan = qa_module.case_plan(seed, 5)
        wants = {}
        letters = []
        for segment in SEGMENTS:
            for category, index, want in plan[segment]:
                kind = qa_module.KINDS[category][index]
                if kind in qa_module.YES_NO_KINDS:
                    wants.setdefault(category, []).append(want)
                elif kind in qa_module.CHOICE_KINDS:
                    letters.append(want)
        per_category = [said.count(True) - said.count(False) for said in wants.values()]
        assert all(abs(d) <= 1 for d in per_category) and abs(sum(per_category)) <= 1, (seed, wants)
        counts = [letters.count(k) for k in range(qa_module.CHOICE_OPTIONS)]
        assert max(counts) - min(counts) <= 1, (seed, letters)


def test_the_scene_description_says_what_the_frames_show_in_the_qas_own_words():
    """describe_scene: setting, lane count and ego lane, weather and surface, road shape and steering, each from the
    truth and in the phrases the QA's answers use; a training-only record, in no clip's benchmark QA."""
    from lanevil_train.vlm.clips.qa import DESCRIBE_QUESTION, describe_scene

    record = describe_scene(truth(), "case-1-before")
    assert record == {"qa_id": "case-1-before-describe", "base_clip_id": "case-1-before",
                      "category": "scene_description", "type": "open", "question": DESCRIBE_QUESTION,
                      "answer": "An urban street between buildings. The road has three lanes; the ego vehicle is in "
                                "the second lane from the left. It is a clear day around noon with bright sunlight. "
                                "The road surface is dry. Curving to the left. The ego vehicle must steer gently to "
                                "the left."}
    night = describe_scene(truth(weather="night", night=True, wet=1.0, num_lanes=4, ego_lane=3, scene_kind="highway",
                                 curvature_sign=0, slope="uphill", markings=["white_solid"] * 5), "c")["answer"]
    assert night == ("A multi-lane highway. The road has four lanes; the ego vehicle is in the rightmost lane. It is "
                     "night, with the road lit by street lamps and headlights. The road surface is wet. "
                     "Climbing uphill. No steering is needed.")
    # a slope hides the bend in the road's shape: the description names it, and the steering it asks for
    hill = describe_scene(truth(curvature_sign=1, slope="downhill"), "c")["answer"]
    assert hill.endswith("Going downhill. Curving to the right. The ego vehicle must steer gently to the right.")
    assert all(qa["question"] != DESCRIBE_QUESTION for qa in make_qa(truth(), "case-1-before", 3))
    with pytest.raises(ValueError, match="num_lanes"):
        describe_scene(truth(num_lanes=9), "c")


def test_mirror_scene_classes_are_the_classes_of_the_mirrored_scene():
    """The mirror image of a 4-lane road, ego in lane 1 of 0..3, bending left between a dashed line and a
    solid-and-dashed pair: ego lane 2, bending right, the markings swapped, and the pair (no name mirrors it)
    unknown; mirroring twice gives the classes back where nothing became unknown."""
    from lanevil_train.vlm.clips.qa import SCENE_CLASSES, UNKNOWN_CLASS, mirror_scene_classes, scene_classes

    markings = ["white_solid", "white_dashed", "yellow_solid_dashed", "white_dashed", "white_solid"]
    classes = scene_classes(truth(num_lanes=4, ego_lane=1, curvature_sign=-1, markings=markings))
    named = {k: (SCENE_CLASSES[k][v] if v != UNKNOWN_CLASS else None)
             for k, v in zip(SCENE_CLASSES, mirror_scene_classes(classes))}
    assert named == {"num_lanes": 4, "ego_lane": 2, "road_shape": "right_curve", "weather": "clear_noon",
                     "scene_kind": "urban", "wet": False, "left_marking": None, "right_marking": "white_dashed",
                     "bend": "right"}
    plain = scene_classes(truth(num_lanes=3, ego_lane=0, curvature_sign=1, slope="uphill"))
    assert mirror_scene_classes(mirror_scene_classes(plain)) == plain != mirror_scene_classes(plain)
    with pytest.raises(ValueError, match="classes: expected 9 class indices"):
        mirror_scene_classes(plain[:-1])
    with pytest.raises(ValueError, match="classes: ego lane 4 on a road of 3 lanes"):
        mirror_scene_classes([plain[0], 4, *plain[2:]])


def test_training_aids_are_the_description_and_open_questions_whose_answers_turn_on_the_frames():
    """training_aids: the description, then the lane count, ego lane, steering and safe action asked openly, each
    answer the truth's (a hill's bend included), phrased as the benchmark's own kinds, the same for the same clip."""
    from lanevil_train.vlm.clips.qa import (
        DESCRIBE_QUESTION,
        EGO_LANE_QUESTIONS,
        LANE_COUNT_QUESTIONS,
        describe_scene,
        training_aids,
    )

    aids = training_aids(truth(num_lanes=4, ego_lane=3, curvature_sign=1, slope="uphill",
                               markings=["white_solid"] * 5), "case-7-over")
    assert [a["qa_id"] for a in aids] == ["case-7-over-describe"] + [f"case-7-over-aid{k}" for k in range(1, 5)]
    assert aids[0] == describe_scene(truth(num_lanes=4, ego_lane=3, curvature_sign=1, slope="uphill",
                                           markings=["white_solid"] * 5), "case-7-over")
    assert aids[0]["question"] == DESCRIBE_QUESTION and all(a["type"] == "open" for a in aids)
    assert aids[1]["question"] in LANE_COUNT_QUESTIONS and aids[1]["answer"] == "The road has four lanes."
    assert aids[2]["question"] in EGO_LANE_QUESTIONS
    assert aids[2]["answer"] == "The ego vehicle is in the rightmost lane; the road has four lanes."
    assert aids[3]["answer"] == "It must steer gently to the right, following the road's curve."
    assert aids[4]["category"] == "action" and aids[4]["answer"].startswith(
        "It should stay in the rightmost lane and follow the road's curve; the dark straight lines in the left lane "
        "are shadows of a roadside rail")
    straight = training_aids(truth(curvature_sign=0), "case-7-over")
    assert straight[3]["answer"].startswith("No steering is needed")
    assert "hold a straight course" in straight[4]["answer"]
    assert [a["question"] for a in straight] == [a["question"] for a in aids]  # phrasing follows the clip id
    with pytest.raises(ValueError, match="truth of c: num_lanes"):
        training_aids(truth(num_lanes=9), "c")


def test_scene_classes_index_each_fact_of_the_truth():
    """scene_classes: the class index of every SCENE_CLASSES fact (what the embedded VLM's tower is pretrained on)."""
    from lanevil_train.vlm.clips.qa import SCENE_CLASSES, scene_classes

    assert list(SCENE_CLASSES) == ["num_lanes", "ego_lane", "road_shape", "weather", "scene_kind", "wet",
                                   "left_marking", "right_marking", "bend"]
    named = dict(zip(SCENE_CLASSES, scene_classes(truth())))
    assert {k: SCENE_CLASSES[k][v] for k, v in named.items()} == {
        "num_lanes": 3, "ego_lane": 1, "road_shape": "left_curve", "weather": "clear_noon", "scene_kind": "urban",
        "wet": False, "left_marking": "white_dashed", "right_marking": "white_dashed", "bend": "left"}
    other = dict(zip(SCENE_CLASSES, scene_classes(truth(num_lanes=4, ego_lane=0, slope="downhill", wet=1.0,
                                                       weather="night", markings=["white_solid"] * 4 + ["none"]))))
    assert {k: SCENE_CLASSES[k][v] for k, v in other.items()} == {
        "num_lanes": 4, "ego_lane": 0, "road_shape": "downhill", "weather": "night", "scene_kind": "urban",
        "wet": True, "left_marking": "white_solid", "right_marking": "white_solid", "bend": "left"}
    with pytest.raises(ValueError, match="truth of c-1: ego_lane"):
        scene_classes(truth(ego_lane=3), "c-1")
