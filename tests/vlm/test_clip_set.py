"""The clip suite on disk (build, resume, read back) and on the fly, against a stand-in renderer."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lanevil_train.vlm.clips import clip_set
from lanevil_train.vlm.clips.clip_set import ClipSetDataset, SyntheticClipSuite, build_clip_set
from lanevil_train.vlm.clips.qa_records import QA_CATEGORIES
from tests.vlm import fake_clips

SIZE = (24, 40)


@pytest.fixture(autouse=True)
def fake_geometry(monkeypatch):
    monkeypatch.setattr(clip_set, "_geometry", lambda: fake_clips)


def cases(n=2):
    return fake_clips.clip_cases(n, 500, ["rail_shadow", "vehicle"])


def snapshot(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_build_writes_clips_qa_and_a_complete_record(tmp_path):
    summary = build_clip_set(cases(), [2, 4], tmp_path, size=SIZE, progress="none")
    assert summary == {"root": str(tmp_path), "clips": 18, "written": 18, "skipped": 0, "qa": 30}
    clips = [json.loads(line) for line in (tmp_path / "clips.jsonl").read_text().splitlines()]
    qas = [json.loads(line) for line in (tmp_path / "qa.jsonl").read_text().splitlines()]
    assert len(clips) == 18 and len(qas) == 30
    first = clips[0]
    assert first == {"clip_id": "case-0000500-before-clean", "base_clip_id": "case-0000500-before",
                     "case_id": "case-0000500", "segment": "before", "illusion": None, "category": None,
                     "severity": 0, "seed": 500, "frames": [f"clips/case-0000500/before/clean/{k}.png"
                                                            for k in range(6)]}
    vehicle = [c for c in clips if c["case_id"] == "case-0000501" and c["severity"] == 4]
    assert [c["category"] for c in vehicle] == ["traffic_obstruction"] * 3
    assert {q["category"] for q in qas} == set(QA_CATEGORIES)
    build = json.loads((tmp_path / "build.json").read_text())
    assert build["complete"] is True and build["clips"] == 18 and build["plan"]["severities"] == [2, 4]

    data = ClipSetDataset(tmp_path)
    assert len(data) == 18 and data.item_key(1) == "case-0000500-before-s2"
    item = data[1]
    rendered = fake_clips.render_clip(cases()[0], "before", [0, 2, 4], SIZE)
    assert all(np.array_equal(a, b) for a, b in zip(item["frames"], rendered[2]))  # PNG is lossless
    assert item["qa"] == data[0]["qa"] and len(item["qa"]) == 5  # shared by the clean clip and its variants
    assert item["meta"] == {k: clips[1][k] for k in clip_set.META_KEYS}
    assert data.clip_meta(1) == item["meta"] and data.qa_for("case-0000500-before") == item["qa"]


def test_interrupted_build_is_refused_then_resumes_to_the_same_files(tmp_path, monkeypatch):
    build_clip_set(cases(), [3], tmp_path / "whole", size=SIZE, progress="none")
    real = clip_set.render_base_clip
    calls = {"n": 0}

    def dies_on_fourth(args):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real(args)

    monkeypatch.setattr(clip_set, "render_base_clip", dies_on_fourth)
    with pytest.raises(KeyboardInterrupt):
        build_clip_set(cases(), [3], tmp_path / "resumed", size=SIZE, progress="none")
    with pytest.raises(ValueError, match=r"incomplete: 6 of 12 clips.*rerun task=build data=clips"):
        ClipSetDataset(tmp_path / "resumed")
    # a torn last QA line and a stale temporary, as a kill can leave them
    with open(tmp_path / "resumed" / "qa.jsonl", "a") as handle:
        handle.write('{"qa_id": "torn')
    (tmp_path / "resumed" / "clips" / ".0.png.1.ab.partial").write_bytes(b"x")
    monkeypatch.setattr(clip_set, "render_base_clip", real)
    summary = build_clip_set(cases(), [3], tmp_path / "resumed", size=SIZE, progress="none")
    assert summary["written"] == 6 and summary["skipped"] == 6
    assert snapshot(tmp_path / "resumed") == snapshot(tmp_path / "whole")
    again = build_clip_set(cases(), [3], tmp_path / "resumed", size=SIZE, progress="none")
    assert again["written"] == 0 and again["skipped"] == 12


def test_rerun_with_another_plan_is_refused(tmp_path):
    build_clip_set(cases(1), [3], tmp_path, size=SIZE, progress="none")
    with pytest.raises(ValueError, match="build.json: out_dir .* holds a clip set built with other cases"):
        build_clip_set(cases(1), [3, 5], tmp_path, size=SIZE, progress="none")


def test_paraphraser_rewrites_questions_and_open_answers_only(tmp_path):
    seen = []

    def shout(texts):
        seen.extend(texts)
        return [t.upper() for t in texts]

    build_clip_set(cases(1), [3], tmp_path, size=SIZE, progress="none", paraphraser=shout)
    qas = [json.loads(line) for line in (tmp_path / "qa.jsonl").read_text().splitlines()]
    assert all(q["question"].isupper() for q in qas)
    assert all(q["answer"].isupper() == (q["type"] == "open") for q in qas)
    assert len(seen) == len(qas) + sum(q["type"] == "open" for q in qas)
    with pytest.raises(ValueError, match="paraphraser: expected a list of"):
        build_clip_set(cases(1), [3], tmp_path / "bad", size=SIZE, progress="none", paraphraser=lambda t: t[:-1])


def test_reader_names_bad_lines_and_missing_frames(tmp_path):
    build_clip_set(cases(1), [3], tmp_path, size=SIZE, progress="none")
    lines = (tmp_path / "clips.jsonl").read_text().splitlines()
    record = json.loads(lines[2])
    record["frames"] = record["frames"][:5]
    (tmp_path / "clips.jsonl").write_text("\n".join(lines[:2] + [json.dumps(record)] + lines[3:]) + "\n")
    with pytest.raises(ValueError, match=r"clips.jsonl:3: frames: expected a list of 6 image paths"):
        ClipSetDataset(tmp_path)
    (tmp_path / "clips.jsonl").write_text("\n".join(lines) + "\n")
    qa_lines = (tmp_path / "qa.jsonl").read_text().splitlines()
    bad = json.loads(qa_lines[1])
    bad["category"] = "weather"
    (tmp_path / "qa.jsonl").write_text("\n".join([qa_lines[0], json.dumps(bad)] + qa_lines[2:]) + "\n")
    with pytest.raises(ValueError, match=r"qa.jsonl:2: category: expected one of scene_description"):
        ClipSetDataset(tmp_path)
    (tmp_path / "qa.jsonl").write_text("\n".join(qa_lines) + "\n")
    (tmp_path / "clips" / "case-0000500" / "over" / "s3" / "5.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"1 frame files are missing .*over/s3/5.png"):
        ClipSetDataset(tmp_path)
    with pytest.raises(FileNotFoundError, match="no build.json"):
        ClipSetDataset(tmp_path / "clips")


def test_a_question_whose_base_clip_is_missing_or_whose_id_repeats_is_refused_by_line(tmp_path):
    build_clip_set(cases(2), [3], tmp_path, size=SIZE, progress="none")
    qa_lines = (tmp_path / "qa.jsonl").read_text().splitlines()
    typo = json.loads(qa_lines[6])
    assert typo["base_clip_id"] == "case-0000500-over"
    typo["base_clip_id"] = "case-0000500-ovr"
    (tmp_path / "qa.jsonl").write_text("\n".join(qa_lines[:6] + [json.dumps(typo)] + qa_lines[7:]) + "\n")
    with pytest.raises(ValueError) as caught:
        ClipSetDataset(tmp_path)
    message = str(caught.value)
    assert message.startswith(f"{tmp_path / 'qa.jsonl'}:7: base_clip_id 'case-0000500-ovr' names no clip of "
                              f"{tmp_path / 'clips.jsonl'}, so QA {typo['qa_id']!r} would never be asked")
    assert message.endswith("nearest base clip ids: case-0000500-over, case-0000501-over, case-0000500-before")
    twice = json.loads(qa_lines[1])
    (tmp_path / "qa.jsonl").write_text("\n".join(qa_lines[:6] + [json.dumps(twice)] + qa_lines[7:]) + "\n")
    with pytest.raises(ValueError, match=rf"qa.jsonl:7: qa_id '{twice['qa_id']}' of base clip "
                                         rf"'case-0000500-before' is given twice \(first at .*qa.jsonl:2\)"):
        ClipSetDataset(tmp_path)


def test_synthetic_suite_matches_the_built_set(tmp_path):
    suite = SyntheticClipSuite(2, 500, ["rail_shadow", "vehicle"], [2, 4], SIZE)
    build_clip_set(suite.cases, [2, 4], tmp_path, size=SIZE, progress="none")
    data = ClipSetDataset(tmp_path)
    assert len(suite) == len(data) == 18
    assert [suite.item_key(i) for i in range(18)] == [data.item_key(i) for i in range(18)]
    fake_clips.CALLS["render"] = 0
    for i in (0, 1, 2, 9):
        assert suite.clip_meta(i) == data.clip_meta(i)
        ours, theirs = suite[i], data[i]
        assert ours["qa"] == theirs["qa"] and ours["meta"] == theirs["meta"]
        assert all(np.array_equal(a, b) for a, b in zip(ours["frames"], theirs["frames"]))
    assert fake_clips.CALLS["render"] == 2  # one render per base clip, cached across its variants
    with pytest.raises(ValueError, match="unknown illusion 'smoke'"):
        SyntheticClipSuite(1, 0, ["smoke"], [1], SIZE)
    with pytest.raises(ValueError, match="num_cases"):
        SyntheticClipSuite(0, 0, "all", [1], SIZE)


def test_a_window_shuffle_renders_each_base_clip_once_per_epoch_and_mixes_clips_within_windows():
    """6 cases = 18 base clips x (clean + 2 severities) x 5 QA = 270 pairs. WindowShuffleSampler(window 4) with a
    suite keeping 4 base clips' renders: every pair once per epoch, each base clip rendered once, windows of 4 base
    clips (20 consecutive pairs span several clips), a new order next epoch, the same order for the same epoch;
    with a 1-clip cache the same order renders far more."""
    from lanevil_train.vlm.clips.qa_data import ClipQADataset, WindowShuffleSampler

    suite = SyntheticClipSuite(6, 500, ["rail_shadow", "vehicle"], [2, 4], SIZE, cache_clips=4)
    pairs = ClipQADataset(suite, "all")
    assert len(pairs) == 18 * 3 * 5
    sampler = WindowShuffleSampler(pairs, window=4, seed=7)
    fake_clips.CALLS["render"] = 0
    order = list(sampler)
    assert sorted(order) == list(range(len(pairs)))
    bases = [pairs.clips.clip_meta(pairs.pairs[i][0])["base_clip_id"] for i in order]
    for i in order:
        pairs[i]
    assert fake_clips.CALLS["render"] == 18  # once per base clip, all its variants at once
    windows = [set(bases[start:start + 60]) for start in range(0, len(bases), 60)]
    assert [len(w) for w in windows] == [4, 4, 4, 4, 2] and set().union(*windows) == set(bases)
    assert len(set(bases[:20])) >= 3  # a batch-sized run mixes the window's clips
    sampler.set_epoch(1)
    assert list(sampler) != order
    sampler.set_epoch(0)
    assert list(sampler) == order
    small_cache = ClipQADataset(SyntheticClipSuite(6, 500, ["rail_shadow", "vehicle"], [2, 4], SIZE), "all")
    fake_clips.CALLS["render"] = 0
    for i in order:
        small_cache[i]
    assert fake_clips.CALLS["render"] > 100
    with pytest.raises(ValueError, match="window: expected an integer >= 1"):
        WindowShuffleSampler(pairs, window=0)
    with pytest.raises(ValueError, match="cache_clips: expected an integer >= 1"):
        SyntheticClipSuite(1, 0, "all", [1], SIZE, cache_clips=0)


def test_aids_add_training_aid_pairs_a_set_on_disk_cannot_give(tmp_path):
    """ClipQADataset(aids=2): each clip variant's 5 QA plus each of its base clip's 8 training aids (description,
    fact questions, a Yes, a No and a choice question) twice, as the truth gives them; a built set has no truth, so
    aids are refused there, naming why."""
    from lanevil_train.vlm.clips.qa import DESCRIBE_QUESTION, training_aids
    from lanevil_train.vlm.clips.qa_data import ClipQADataset
    from lanevil_train.vlm.clips.qa_records import prompt_text

    suite = SyntheticClipSuite(1, 500, ["rail_shadow"], [2], SIZE)
    pairs = ClipQADataset(suite, "all", aids=2)
    assert len(pairs) == 3 * 2 * (5 + 2 * 8) == len(ClipQADataset(suite, "all")) + 96
    items = [pairs[i] for i in range(len(pairs))]
    described = [item for item in items if item["question"] == DESCRIBE_QUESTION]
    assert len(described) == 12 and {item["meta"]["severity"] for item in described} == {0, 2}
    base = described[0]["meta"]["base_clip_id"]
    case, segment = suite.by_base[base]
    expected = training_aids(fake_clips.clip_truth(case, segment, SIZE), base)
    of_base = [item for item in items if item["meta"]["base_clip_id"] == base and item["meta"]["severity"] == 0]
    aid_items = [item for item in of_base if item["meta"]["qa_id"] in {aid["qa_id"] for aid in expected}]
    assert [(item["question"], item["answer"]) for item in aid_items] == \
        [(prompt_text(aid), aid["answer"]) for aid in expected] * 2  # a choice aid is asked with its options
    assert described[0]["key"].endswith(f"/{base}-describe")
    build_clip_set(suite.cases, [2], tmp_path, size=SIZE, progress="none")
    with pytest.raises(ValueError, match="aids: 1 rounds of training aids need the scene truth, which "
                                         "ClipSetDataset does not keep"):
        ClipQADataset(ClipSetDataset(tmp_path), "all", aids=1)
    with pytest.raises(ValueError, match="aids: expected an integer >= 0"):
        ClipQADataset(suite, "all", aids=-1)
