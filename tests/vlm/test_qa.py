"""QA from the simulator's truth: categories, reference answers true to the scene, the accuracy rule, and a suite
whose wordings give no answer away (each yes/no template as often Yes as No, choice options evenly right,
counterfactual twins asked in the same words)."""

from __future__ import annotations

from collections import Counter, defaultdict

import numpy as np
import pytest

from lanevil_train.vlm.clips import qa as qa_module
from lanevil_train.vlm.clips import qa_closed
from lanevil_train.vlm.clips.qa import clip_categories
from lanevil_train.vlm.clips.qa_facts import CUE_GROUP, ILLUSION_FACTS, NATURE
from lanevil_train.vlm.clips.qa_records import QA_CATEGORIES, answer_is_correct, chosen_letter
from lanevil_train.vlm.clips.suite_qa import suite_qa
from tests.vlm.truth_fixture import truth

SEGMENTS = ("before", "over", "alongside")


def candidates(t: dict) -> dict[str, dict]:
    """Every closed question a clip of truth `t` could be asked, by template."""
    return {c["template"]: c for kinds in qa_closed.CLOSED_KINDS.values() for kind in kinds for c in kind(t)}


def opens(t: dict, seeds=range(20)) -> list[dict]:
    return [kind(t, np.random.default_rng(s)) for kinds in qa_module.OPEN_KINDS.values() for kind in kinds
            for s in seeds]


def test_five_qa_per_clip_and_one_case_covers_all_six_categories():
    planned = suite_qa([(f"case-{seg}", 7, truth(segment=seg)) for seg in SEGMENTS])
    every = [qa for seg in SEGMENTS for qa in planned[f"case-{seg}"]]
    assert len(every) == 15 and {qa["category"] for qa in every} == set(QA_CATEGORIES)
    for seg in SEGMENTS:
        clip = planned[f"case-{seg}"]
        assert len({qa["category"] for qa in clip}) == 5
        assert [qa["qa_id"] for qa in clip] == [f"case-{seg}-q{k}" for k in range(5)]
        assert all(qa["template"] == qa["question"] for qa in clip)
    missing = [set(QA_CATEGORIES) - set(clip_categories(7, seg, 5)) for seg in SEGMENTS]
    assert len(set().union(*missing)) == 3  # each segment leaves out a different category
    # one case alone answers a closed template both ways only where its segments differ (where the car is)
    closed = {qa["template"] for qa in every if qa["type"] != "open"}
    answers = {t: {str(candidates(truth(segment=seg)).get(t)) for seg in SEGMENTS} for t in closed}
    assert all(len(said) >= 2 for said in answers.values()), answers


def test_deterministic_given_the_suite_and_different_for_another():
    clips = [(f"c{s}-{seg}", s, truth(segment=seg, num_lanes=2 + s % 4, ego_lane=0, markings=["white_solid"] *
                                      (3 + s % 4), night=bool(s % 3 == 0), illusion=list(CUE_GROUP)[s % 14]))
             for s in range(30) for seg in SEGMENTS]
    assert suite_qa(clips) == suite_qa([(b, s, dict(t)) for b, s, t in clips])
    assert suite_qa(clips) != suite_qa(clips[3:])


@pytest.mark.parametrize("lanes", [2, 3, 4, 5])
def test_lane_count_is_the_renderers_lane_count(lanes):
    t = truth(num_lanes=lanes, ego_lane=0, markings=["yellow_solid"] + ["white_dashed"] * (lanes - 1) +
              ["white_solid"])
    words = {2: "two", 3: "three", 4: "four", 5: "five"}
    counts = [c for c in candidates(t).values() if c["template"].startswith(("How many", "Count the"))]
    assert counts and all(c["correct"] == f"{words[lanes].capitalize()} lanes." for c in counts)
    said = {c["template"]: c["yes"] for c in candidates(t).values() if c["template"].startswith("Does this road have")}
    assert said == {f"Does this road have {words[k]} lanes?": k == lanes for k in (2, 3, 4, 5)}
    assert all(words[lanes] in qa["answer"] for qa in opens(t) if qa["question"].startswith(("How many", "Count")))


def test_answers_follow_the_truth():
    night, day = candidates(truth(weather="night", night=True)), candidates(truth())
    assert night["Is this clip recorded at night?"]["yes"] and not day["Is this clip recorded at night?"]["yes"]
    assert day["Is it daytime in this scene?"]["yes"] and not night["Is it daytime in this scene?"]["yes"]
    ego = candidates(truth(ego_lane=2))
    assert ego["Which lane is the ego vehicle driving in?"]["correct"] == "The third lane from the left."
    assert ego["Is the ego vehicle in the rightmost lane?"]["yes"] and not ego["Is the ego vehicle in the leftmost "
                                                                               "lane?"]["yes"]
    # left of ego lane 1 is white_dashed (crossable); ego lane 0's left is the road's left edge
    change = "May the ego vehicle change to the lane on its left here?"
    assert candidates(truth())[change]["yes"] and "dashed white" in candidates(truth())[change]["reason"]
    assert not candidates(truth(markings=["yellow_solid", "white_solid", "white_dashed", "white_solid"]))[change]["yes"]
    assert not candidates(truth(ego_lane=0))[change]["yes"]
    shape = "How does the road run ahead of the ego vehicle?"
    assert candidates(truth(slope="uphill", curvature_sign=0))[shape]["correct"] == "Climbing uphill."
    # an s-curve scene whose clip bends right, on the level: the clip's shape, not the scene's road kind
    assert candidates(truth(road="s_curve", curvature_sign=1))[shape]["correct"] == "Curving to the right."
    marked = candidates(truth())
    assert marked["Is the line on the left of the ego lane white?"]["yes"]
    assert not marked["Is the line on the left of the ego lane yellow?"]["yes"]
    assert marked["Is the ego lane marked on its right by a dashed white line?"]["yes"]
    assert not marked["Is the ego lane marked on its right by a solid white line?"]["yes"]
    fast = candidates(truth(ego_speed_mps=15.0))
    assert fast["Is the ego vehicle driving faster than 50 km/h?"]["yes"]  # 54 km/h
    assert not candidates(truth(ego_speed_mps=10.0))["Is the ego vehicle driving faster than 40 km/h?"]["yes"]


def test_counterfactual_twins_are_asked_in_the_same_words_and_answered_the_other_way():
    """Illusions are named by what a camera sees: every cue is shared by illusions of two natures, so the same
    words ask about a shadow in one scene and a crack, a real rail or a real vehicle in its twin."""
    for group in set(CUE_GROUP.values()):
        assert len({NATURE[name] for name in CUE_GROUP if CUE_GROUP[name] == group}) == 2, group
    for name, facts in ILLUSION_FACTS.items():  # the cue never says what it is
        said = qa_closed.cue(truth(illusion=name)).split()
        assert not {"shadow", "shadows", "crack", "cracks", "reflection", "reflections", "rail"} & set(said), name
    twins = (("rail_shadow", "road_crack", "left", "Are the dark lines in the left lane shadows or reflections of "
                                                    "light?"),
             ("guard_rail", "sunlight_reflection", "right_shoulder", "Do the bright streaks on the right shoulder "
                                                                     "stand up above the road surface?"),
             ("vehicle", "vehicle_reflection", "ego", "Must the ego vehicle stop before the shapes of people or "
                                                      "vehicles in the ego lane?"))
    for first, second, lane, question in twins:
        a = candidates(truth(illusion=first, illusion_lane=lane))[question]
        b = candidates(truth(illusion=second, illusion_lane=lane))[question]
        assert a["type"] == b["type"] == "yes_no" and a["yes"] is True and b["yes"] is False, question
    # the real vehicle blocks the ego lane: the safe action is to stop, in the words every scene is asked
    action = "What should the ego vehicle do next?"
    stop = candidates(truth(illusion="vehicle", illusion_lane="ego"))[action]["correct"]
    assert stop == "Slow down and stop behind what blocks its lane."
    assert candidates(truth(illusion="vehicle_reflection", illusion_lane="ego"))[action]["correct"] == \
        "Follow the road's bend to the left in its lane."
    assert candidates(truth(curvature_sign=0))[action]["correct"] == "Keep driving straight on in its lane."
    assert candidates(truth(curvature_sign=1))[action]["correct"] == "Follow the road's bend to the right in its lane."


def test_traffic_is_passed_not_driven_over():
    question = "Relative to the shapes of people or vehicles in the left lane, what is the ego vehicle doing?"
    for illusion, seg, expected in (("vehicle", "over", "Closing in on them"), ("vehicle", "alongside", "Passing"),
                                    ("vehicle_reflection", "over", "Driving over them")):
        said = candidates(truth(illusion=illusion, illusion_lane="left", segment=seg))[question]["correct"]
        assert said.startswith(expected), (illusion, seg, said)
    blocked = candidates(truth(illusion="pedestrian", illusion_lane="ego", segment="alongside"))
    assert blocked["Relative to the shapes of people or vehicles in the ego lane, what is the ego vehicle "
                   "doing?"]["correct"] == "Stopping behind them."
    assert not blocked["Does the ego vehicle reach the shapes of people or vehicles in the ego lane during this "
                       "clip?"]["yes"]


def test_every_answer_has_its_form():
    planned = suite_qa([(f"c{s}-{seg}", s, truth(segment=seg, night=bool(s % 2), illusion=list(CUE_GROUP)[s % 14]))
                        for s in range(40) for seg in SEGMENTS])
    every = [qa for qas in planned.values() for qa in qas] + opens(truth()) + opens(truth(illusion="pedestrian"))
    assert {qa["type"] for qa in every} == {"open", "yes_no", "choice"}
    for qa in every:
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
        suite_qa([("c", 0, {k: v for k, v in truth().items() if k != "num_lanes"})])
    with pytest.raises(ValueError, match="illusion_lane: expected one of ego, left"):
        suite_qa([("c", 0, truth(illusion_lane="middle"))])
    with pytest.raises(ValueError, match="markings: expected num_lanes \\+ 1"):
        suite_qa([("c", 0, truth(markings=["white_solid"]))])
    with pytest.raises(ValueError, match="per_clip"):
        suite_qa([("c", 0, truth())], per_clip=0)


# ---------------------------------------------------------------------------------------------- fairness on a suite

def _suite(cases: int, first_seed: int) -> list[tuple[dict, list[dict]]]:
    """(truth, QA) of every base clip of a suite with all 14 illusions, from the renderer's truth (no frames)."""
    from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite

    suite = SyntheticClipSuite(cases, first_seed, "all", (3,), (64, 112))
    return [(suite._truth(base), suite.qa_for(base)) for base in suite.by_base]


@pytest.fixture(scope="module")
def suite():
    return _suite(120, 1000000)


def test_every_yes_no_template_is_asked_as_often_yes_as_no(suite):
    """The old generator chose each wording so that the truth answered it its way: a text-only classifier answered
    85.5 % of yes/no questions of held-out scenes."""
    answers = defaultdict(list)
    for _, qas in suite:
        for qa in qas:
            if qa["type"] == "yes_no":
                answers[qa["template"]].append(qa["answer"].startswith("Yes."))
    assert sum(map(len, answers.values())) >= 400 and len(answers) >= 60
    assert {t: (sum(a), len(a)) for t, a in answers.items() if 2 * sum(a) != len(a)} == {}
    by_category = Counter(qa["category"] for _, qas in suite for qa in qas if qa["type"] == "yes_no")
    assert set(by_category) == set(QA_CATEGORIES) and min(by_category.values()) >= 30, by_category


def test_choice_options_are_evenly_right_and_letters_uniform(suite):
    choices = [qa for _, qas in suite for qa in qas if qa["type"] == "choice"]
    assert len(choices) >= 300
    by_template = defaultdict(list)
    for qa in choices:
        by_template[qa["template"]].append(qa)
        assert 2 <= len(qa["choices"]) <= 4 and len(set(qa["choices"])) == len(qa["choices"])
    judged = 0
    for template, qas in by_template.items():
        right = Counter(qa["answer"][3:] for qa in qas)
        assert len(right) >= 2 or len(qas) < 4, template  # the correct option's text varies
        if len(qas) >= 20:
            judged += 1
            options = min(len(qa["choices"]) for qa in qas)
            assert right.most_common(1)[0][1] / len(qas) <= 1 / options + 0.10, (template, right)
    assert judged >= 5
    for count in (3, 4):
        letters = Counter(qa["answer"][0] for qa in choices if len(qa["choices"]) == count)
        assert max(letters.values()) - min(letters.values()) <= 2 and len(letters) == count, (count, letters)


def test_a_text_only_reader_scores_chance_on_held_out_scenes(suite):
    from lanevil_train.vlm.backends.text_only import TextOnlyReader

    reader = TextOnlyReader().fit([qa for _, qas in suite for qa in qas])
    held = [qa for _, qas in _suite(40, 2000000) for qa in qas]
    for kind in ("yes_no", "choice"):
        asked = [qa for qa in held if qa["type"] == kind]
        accuracy = np.mean([answer_is_correct(qa, reader.predict(qa)) for qa in asked])
        chance = np.mean([0.5 if kind == "yes_no" else 1 / len(qa["choices"]) for qa in asked])
        assert len(asked) >= 80 and abs(accuracy - chance) <= 0.10, (kind, accuracy, chance, len(asked))


def test_reference_answers_match_the_renderers_truth(suite):
    checked = Counter()
    for t, qas in suite:
        said = candidates(t)
        for qa in qas:
            if qa["type"] == "yes_no":
                assert qa["answer"].startswith("Yes." if said[qa["template"]]["yes"] else "No."), qa
            elif qa["type"] == "choice":
                assert qa["answer"][3:] == said[qa["template"]]["correct"], qa
            checked[qa["type"]] += 1
            if qa["template"].startswith(("How many", "Count the")):
                assert ("two", "three", "four", "five")[t["num_lanes"] - 2] in qa["answer"].lower()
            if qa["template"] == "Is the ego vehicle in the leftmost lane?":
                assert qa["answer"].startswith("Yes.") == (t["ego_lane"] == 0)
    assert checked["yes_no"] >= 400 and checked["choice"] >= 300


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
    assert all(qa["question"] != DESCRIBE_QUESTION for qa in opens(truth()))
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
    answer the truth's (a hill's bend included), phrased as the benchmark's own kinds, the same for the same clip;
    then a closed question the clip answers Yes, one it answers No and a choice, each its closed kind's answer."""
    from lanevil_train.vlm.clips.qa import (
        DESCRIBE_QUESTION,
        EGO_LANE_QUESTIONS,
        LANE_COUNT_QUESTIONS,
        describe_scene,
        training_aids,
    )

    aids = training_aids(truth(num_lanes=4, ego_lane=3, curvature_sign=1, slope="uphill",
                               markings=["white_solid"] * 5), "case-7-over")
    hill = truth(num_lanes=4, ego_lane=3, curvature_sign=1, slope="uphill", markings=["white_solid"] * 5)
    assert [a["qa_id"] for a in aids] == ["case-7-over-describe"] + [f"case-7-over-aid{k}" for k in range(1, 8)]
    assert aids[0] == describe_scene(hill, "case-7-over")
    assert aids[0]["question"] == DESCRIBE_QUESTION and all(a["type"] == "open" for a in aids[:5])
    assert [a["type"] for a in aids[5:]] == ["yes_no", "yes_no", "choice"]
    said = candidates(hill)
    assert aids[5]["answer"].startswith("Yes.") and said[aids[5]["question"]]["yes"] is True
    assert aids[6]["answer"].startswith("No.") and said[aids[6]["question"]]["yes"] is False
    assert aids[7]["answer"][3:] == said[aids[7]["question"]]["correct"] and aids[7]["answer"] in aids[7]["choices"]
    assert aids[1]["question"] in LANE_COUNT_QUESTIONS and aids[1]["answer"] == "The road has four lanes."
    assert aids[2]["question"] in EGO_LANE_QUESTIONS
    assert aids[2]["answer"] == "The ego vehicle is in the rightmost lane; the road has four lanes."
    assert aids[3]["answer"] == "It must steer gently to the right, following the road's curve."
    assert aids[4]["category"] == "action" and aids[4]["answer"].startswith(
        "It should stay in the rightmost lane and follow the road's curve; the dark lines in the left lane "
        "are shadows of a roadside rail")
    straight = training_aids(truth(curvature_sign=0), "case-7-over")
    assert straight[3]["answer"].startswith("No steering is needed")
    assert "hold a straight course" in straight[4]["answer"]
    assert [a["question"] for a in straight[:5]] == [a["question"] for a in aids[:5]]  # phrasing follows the clip id
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


def test_the_audit_finds_no_leak_in_the_suite(suite):
    """task=audit_qa's cross-fitted reader on this benchmark's own QA: no template gives its answer away, and the
    reader does no better than chance (it does worse: each template is exactly balanced over the suite, so the
    scenes it is fitted on hold the opposite majority of the ones it answers)."""
    from lanevil_train.vlm.answer_scoring.leakage import audit

    records = [{**qa, "scene": t["case_id"]} for t, qas in suite for qa in qas]
    result = audit(records, folds=2, seed=0, min_count=8, alpha=0.01)
    assert result["leaking"] == [] and result["settings"]["templates_judged"] >= 20
    for row in result["by_type"]:
        assert row["text_only_accuracy"] <= row["chance"] + 10, row
