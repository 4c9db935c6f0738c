"""The corruption and combined-illusion clip suites (vlm/clips/clips.py render_variants, vlm/clips/clip_set.py
kinds), with the real renderer at a tiny size."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lanevil_train.illusions import get_illusion
from lanevil_train.illusions.context import context_for_frame
from lanevil_train.perturbations import combined_choice
from lanevil_train.taxonomy import CATEGORIES, ILLUSION_CATEGORY
from lanevil_train.vlm.clips import clips
from lanevil_train.vlm.clips.clip_set import (
    ClipSetDataset,
    SyntheticClipSuite,
    build_clip_set,
    kept_questions,
    suite_base_clips,
    variant_records,
)
from lanevil_train.vlm.clips.clips import (
    SEGMENTS,
    ClipCase,
    combined_clip_cases,
    frame_seed,
    reference_scene,
    render_variants,
    segment_positions,
    suite_cases,
)
from lanevil_train.vlm.clips.suite_qa import suite_qa
from tests.vlm.truth_fixture import truth

SIZE = (48, 80)
CORRUPTIONS = ["gaussian_noise", "fog"]


def differs(a, b) -> bool:
    return not np.array_equal(a, b)


def test_corruption_variants_are_the_clean_frames_corrupted_with_a_seed_per_frame():
    from lanevil_train.corruptions import get_corruption

    case = ClipCase("clip-7", 7, "road_crack")
    out = render_variants(case, "over", CORRUPTIONS, [0, 2, 4], SIZE)
    assert sorted(out, key=str) == sorted([(None, 0)] + [(n, s) for n in CORRUPTIONS for s in (2, 4)], key=str)
    clean = out[(None, 0)]
    for name in CORRUPTIONS:
        for sev in (2, 4):
            frames = out[(name, sev)]
            assert len(frames) == 6 and all(f.shape == (*SIZE, 3) and f.dtype == np.uint8 for f in frames)
            for k, (c, f) in enumerate(zip(clean, frames)):
                assert differs(c, f)
                assert np.array_equal(f, get_corruption(name)(c, None, sev, frame_seed(7, "over", k)))
    # the noise pattern changes from frame to frame: consecutive residuals are uncorrelated (one seed for all
    # frames would repeat the pattern: correlation ~0.98)
    noise = [(out[("gaussian_noise", 4)][k].astype(float) - clean[k]).ravel() for k in range(6)]
    assert all(abs(np.corrcoef(noise[k], noise[k + 1])[0, 1]) < 0.2 for k in range(5))
    repeated = get_corruption("gaussian_noise")(clean[1], None, 4, frame_seed(7, "over", 0)).astype(float) - clean[1]
    assert np.corrcoef(repeated.ravel(), noise[0])[0, 1] > 0.9
    seeds = {frame_seed(7, s, k) for s in SEGMENTS for k in range(6)}
    assert len(seeds) == 18 and frame_seed(7, "over", 0) != frame_seed(8, "over", 0)
    clips._reference.cache_clear()
    again = render_variants(case, "over", CORRUPTIONS, [2, 4], SIZE)
    assert all(np.array_equal(a, b) for key in out for a, b in zip(out[key], again[key]))
    records = variant_records(case, "over", [2, 4], "corruptions", CORRUPTIONS)
    assert [r["clip_id"] for r in records] == ["clip-7-over-clean", "clip-7-over-gaussian_noise-s2",
                                               "clip-7-over-gaussian_noise-s4", "clip-7-over-fog-s2",
                                               "clip-7-over-fog-s4"]
    assert [(r["illusion"], r["category"], r["severity"]) for r in records] == [
        (None, None, 0), ("gaussian_noise", "noise", 2), ("gaussian_noise", "noise", 4), ("fog", "weather", 2),
        ("fog", "weather", 4)]
    assert records[3]["frames"][5] == "clips/clip-7/over/fog-s2/5.png"


def test_combined_cases_cover_the_six_category_pairs_with_the_seeds_draws():
    cases = combined_clip_cases(12, 100)
    pairs = [(ILLUSION_CATEGORY[c.illusion], ILLUSION_CATEGORY[c.second]) for c in cases]
    categories = list(CATEGORIES)
    expected = [(a, b) for i, a in enumerate(categories) for b in categories[i + 1:]]
    assert pairs == expected * 2  # the paper's order RD+TO, RD+SH, RD+RF, TO+SH, TO+RF, SH+RF, twice
    for case in cases:
        singles = combined_choice(case.seed, list(ILLUSION_CATEGORY))[0]
        assert case.illusion in singles and case.second in singles
    assert combined_clip_cases(12, 100) == cases
    # two categories named: every case pairs them
    only = combined_clip_cases(3, 0, ["road_crack", "vehicle", "bicycle"])
    assert [(c.illusion, ILLUSION_CATEGORY[c.second]) for c in only] == [("road_crack", "traffic_obstruction")] * 3
    assert suite_cases("combined", 2, 100) == cases[:2]
    assert [c.illusion for c in suite_cases("corruptions", 3, 0, CORRUPTIONS)] == ["road_crack", "road_repair",
                                                                                   "tire_marks"]


def test_the_pair_variant_draws_the_second_illusion_over_the_first():
    case = combined_clip_cases(6, 100)[3]  # pedestrian + streetlight_shadow
    a, b = case.illusion, case.second
    pair = f"{a}+{b}"
    out = render_variants(case, "over", [a, b, pair], [3], SIZE)
    scene, ref = reference_scene(case, SIZE), clips._reference(case.seed, a, SIZE)[0]
    for k, s0 in enumerate(segment_positions(case, "over", SIZE)):
        ctx = context_for_frame(scene, float(s0), ref)
        first = out[(a, 3)][k]
        assert np.array_equal(first, get_illusion(a)(out[(None, 0)][k], ctx, 3, case.seed))
        assert np.array_equal(out[(b, 3)][k], get_illusion(b)(out[(None, 0)][k], ctx, 3, case.seed))
        assert np.array_equal(out[(pair, 3)][k], get_illusion(b)(first, ctx, 3, case.seed))
    clean, paired = out[(None, 0)], out[(pair, 3)]
    for other in (clean, out[(a, 3)], out[(b, 3)]):
        assert sum(differs(x, y) for x, y in zip(other, paired)) >= 5
    # asked alone, the pair is drawn from scratch with the same pixels
    alone = render_variants(case, "over", [pair], [3], SIZE)[(pair, 3)]
    assert all(np.array_equal(x, y) for x, y in zip(alone, paired))
    records = variant_records(case, "over", [3], "combined")
    assert [(r["clip_id"], r["illusion"], r["category"]) for r in records] == [
        ("clip-103-over-clean", None, None), ("clip-103-over-pedestrian-s3", "pedestrian", "traffic_obstruction"),
        ("clip-103-over-streetlight_shadow-s3", "streetlight_shadow", "shadow"),
        ("clip-103-over-pedestrian+streetlight_shadow-s3", pair, "traffic_obstruction+shadow")]


def test_corruption_suite_qa_leaves_out_what_the_frames_no_longer_show():
    """A corruption suite asks only kinds that work on a truth without the illusion, weather and light (so they
    cannot read the illusion, which is not drawn, nor what weather and brightness corruptions change); the others
    need them. Slots whose category keeps no open kind are left out, the others keep their numbers."""
    from lanevil_train.vlm.clips.qa import OPEN_KINDS
    from lanevil_train.vlm.clips.qa_closed import CLOSED_KINDS
    from lanevil_train.vlm.clips.suite_qa import allowed_kinds

    hidden = ("illusion", "illusion_lane", "category", "weather", "wet", "night")
    blind = {k: v for k, v in truth().items() if k not in hidden}
    for kinds in [*CLOSED_KINDS.values(), *OPEN_KINDS.values()]:
        for kind in kinds:
            args = (blind,) if kinds in CLOSED_KINDS.values() else (blind, np.random.default_rng(0))
            if kind in allowed_kinds(kinds, "corruptions"):
                kind(*args)
            else:
                with pytest.raises(KeyError):
                    kind(*args)
    assert allowed_kinds(OPEN_KINDS["object_recognition"], "corruptions") == ()
    clips = [(f"c{s}-{g}", s, truth(segment=g, num_lanes=2 + s % 3, ego_lane=0, curvature_sign=s % 3 - 1,
                                    markings=[("white_solid", "yellow_solid", "white_dashed")[s % 3]] * (3 + s % 3)))
             for s in range(40) for g in SEGMENTS]
    ours = suite_qa(clips, 5, "corruptions")
    kept_total = 0
    for base, seed, t in clips:
        kept = kept_questions("corruptions", seed, t["segment"], 5)
        assert kept_questions("illusions", seed, t["segment"], 5) == kept_questions("combined", seed, t["segment"],
                                                                                    5) == tuple(range(5))
        assert [int(qa["qa_id"].rsplit("-q", 1)[1]) for qa in ours[base]] == list(kept)
        seen_blind = {**t, **{k: None for k in hidden}}
        for qa in ours[base]:
            assert qa["category"] != "object_recognition"
            if qa["type"] == "open":
                said = {kind(t, np.random.default_rng(r))["question"] for r in range(20)
                        for kind in allowed_kinds(OPEN_KINDS[qa["category"]], "corruptions")}
            else:
                said = {c["template"] for kind in allowed_kinds(CLOSED_KINDS[qa["category"]], "corruptions")
                        for c in kind(seen_blind)}
            assert qa["question"] in said, qa
        kept_total += len(kept)
    assert sum(qa["type"] != "open" for qas in ours.values() for qa in qas) >= 100
    assert 0.5 < kept_total / (40 * 3 * 5) < 0.95
    cases = [ClipCase(f"c{s}", s, "road_crack") for s in range(40)]
    assert len(suite_base_clips(cases, "corruptions")) == sum(bool(kept_questions("corruptions", s, g, 5))
                                                              for s in range(40) for g in SEGMENTS)
    assert len(suite_base_clips(cases, "illusions")) == 120


@pytest.mark.parametrize("kind,names,per_base", [("illusions", ["pedestrian"], 2), ("corruptions", CORRUPTIONS, 3),
                                                 ("combined", "all", 4)])
def test_each_kind_builds_on_disk_and_reads_back_as_the_synthetic_suite(tmp_path, kind, names, per_base):
    suite = SyntheticClipSuite(1, 103, names, [2], SIZE, kind=kind)
    summary = build_clip_set(suite.cases, [2], tmp_path, size=SIZE, progress="none", kind=kind, names=names)
    bases = len(suite_base_clips(suite.cases, kind))
    assert summary["clips"] == summary["written"] == len(suite) == bases * per_base
    data = ClipSetDataset(tmp_path)
    assert data.kind == kind and len(data) == len(suite)
    plan = json.loads((tmp_path / "build.json").read_text())["plan"]
    assert ("kind" in plan) == (kind != "illusions")  # an illusion suite's record is as before suite kinds
    for i in range(len(data)):
        assert data.item_key(i) == suite.item_key(i) and data.clip_meta(i) == suite.clip_meta(i)
        ours, theirs = suite[i], data[i]
        assert ours["qa"] == theirs["qa"] and len(theirs["qa"]) == suite.qa_count(ours["meta"]["base_clip_id"]) > 0
        assert all(np.array_equal(a, b) for a, b in zip(ours["frames"], theirs["frames"]))
    names_seen = {data.clip_meta(i)["illusion"] for i in range(len(data))} - {None}
    case = suite.cases[0]  # combined: case 0 takes the first category pair, road damage + traffic obstruction
    expected = {"illusions": {"pedestrian"}, "corruptions": set(CORRUPTIONS),
                "combined": {case.illusion, case.second, f"{case.illusion}+{case.second}"}}[kind]
    assert names_seen == expected
    if kind == "combined":
        assert (ILLUSION_CATEGORY[case.illusion], ILLUSION_CATEGORY[case.second]) == ("road_damage",
                                                                                      "traffic_obstruction")


def test_a_rerun_with_another_kind_or_names_is_refused_and_an_old_set_reads_as_illusions(tmp_path):
    cases = [ClipCase("clip-103", 103, "pedestrian")]
    build_clip_set(cases, [2], tmp_path, size=SIZE, progress="none")
    with pytest.raises(ValueError, match="holds a clip set built with other cases or another plan"):
        build_clip_set(cases, [2], tmp_path, size=SIZE, progress="none", kind="corruptions", names=CORRUPTIONS)
    record = json.loads((tmp_path / "build.json").read_text())
    assert "kind" not in record["plan"] and ClipSetDataset(tmp_path).kind == "illusions"
    build_clip_set(cases, [2], tmp_path / "c", size=SIZE, progress="none", kind="corruptions", names=["fog"])
    with pytest.raises(ValueError, match="another plan"):
        build_clip_set(cases, [2], tmp_path / "c", size=SIZE, progress="none", kind="corruptions", names=["snow"])


def test_bad_kinds_names_and_cases_are_named(tmp_path):
    case = ClipCase("clip-1", 1, "road_crack")
    with pytest.raises(ValueError, match="kind"):
        build_clip_set([case], [2], tmp_path, size=SIZE, kind="weather")
    with pytest.raises(ValueError, match=r"illusions\[1\]: .*'puddle'"):
        SyntheticClipSuite(1, 0, ["fog", "puddle"], [2], SIZE, kind="corruptions")
    with pytest.raises(ValueError, match=r"illusions\[0\]: .*'fog'"):
        combined_clip_cases(1, 0, ["fog"])
    with pytest.raises(ValueError, match="cases: clip-1 has no second illusion"):
        build_clip_set([case], [2], tmp_path, size=SIZE, kind="combined")
    with pytest.raises(ValueError, match=r"cases\[0\]: clip-1 draws road_crack and vehicle"):
        build_clip_set([ClipCase("clip-1", 1, "road_crack", "vehicle")], [2], tmp_path, size=SIZE, kind="combined",
                       names=["road_crack", "fence_shadow"])
    with pytest.raises(ValueError, match="second: expected an illusion of another category"):
        ClipCase("clip-1", 1, "road_crack", "tire_marks")
    with pytest.raises(ValueError, match=r"names\[0\]: unknown perturbation 'smoke'"):
        render_variants(case, "over", ["smoke"], [1], SIZE)
    assert not (tmp_path / "build.json").exists()


def test_prepare_renders_in_worker_processes_what_the_suite_gives_one_by_one():
    """SyntheticClipSuite.prepare: the facts of every base clip asked and the frames of those to render, from 2
    spawned processes, equal to what qa_for and __getitem__ compute here, in the order asked; the QA are planned
    with the whole suite, so every base clip's truth is then known."""
    suite = SyntheticClipSuite(2, 40, ["rail_shadow", "vehicle"], severities=[2, 4], size=(32, 48))
    bases = list(dict.fromkeys(suite.clip_meta(i)["base_clip_id"] for i in range(len(suite))))
    rendered = suite.prepare(bases[1:], render=[bases[4], bases[2]], workers=2, progress="none")
    assert list(rendered) == [bases[4], bases[2]] and set(suite._truths) == set(bases)
    fresh = SyntheticClipSuite(2, 40, ["rail_shadow", "vehicle"], severities=[2, 4], size=(32, 48))
    for base in bases[1:]:
        assert suite.qa_for(base) == fresh.qa_for(base) and suite.lanes_for(base) == fresh.lanes_for(base)
        assert suite.scene_classes_for(base) == fresh.scene_classes_for(base)
    for base, variants in rendered.items():
        items = [i for i in range(len(fresh)) if fresh.clip_meta(i)["base_clip_id"] == base]
        assert len(variants) == len(items) == 3  # clean, severity 2, severity 4
        for frames, index in zip(variants, items):
            assert all(np.array_equal(a, b) for a, b in zip(frames, fresh[index]["frames"]))
    with pytest.raises(ValueError, match=r"render: expected base clips among base_clip_ids, got \['clip-40-before'\]"):
        suite.prepare(bases[1:], render=[bases[0]])
