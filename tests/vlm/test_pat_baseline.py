"""PAT (Mo et al. 2024), the textual baseline: wrong answers to push toward, the attack suffix's place after the
question, and the alternating tuning of prefix and suffix with its resume."""

from __future__ import annotations

import pytest
import torch

from lanevil_train.vlm.backends.hf import IGNORE_INDEX
from lanevil_train.vlm.defenses.gcg import (
    ControlObjective,
    Examples,
    Part,
    allowed_tokens,
    initial_prefix,
    splice_prefix,
    splice_suffix,
)
from lanevil_train.vlm.defenses.pat_baseline import PATSettings, tune_pat, wrong_answer

QUESTIONS = ["Is the dark line in the left lane a lane marking?", "How many lanes are there?"]
ANSWERS = ["No. It is the shadow of a rail.", "B. Three lanes."]


def test_the_wrong_answer_is_the_other_yes_no_or_another_option():
    assert wrong_answer({"type": "yes_no", "answer": "No. It is the shadow of a rail."}) == "Yes."
    assert wrong_answer({"type": "yes_no", "answer": "Yes, it is."}) == "No."
    choice = {"type": "choice", "answer": "B. Three lanes.", "choices": ["A. Two.", "B. Three lanes.", "C. Four."]}
    assert [wrong_answer(choice, k) for k in range(3)] == ["A. Two.", "C. Four.", "A. Two."]
    assert wrong_answer({"type": "open", "answer": "The road bends left."}) is None


@pytest.mark.parametrize("family", ["qwen2_vl", "llava"])
def test_the_attack_suffix_follows_the_question_and_the_prefix_precedes_it(family, tiny_hf_vlm, small_clips):
    vlm = tiny_hf_vlm(family)
    tokenizer = vlm.processor.tokenizer
    allowed = allowed_tokens(tokenizer, vlm.model.get_input_embeddings().num_embeddings)
    prefix, suffix = initial_prefix(tokenizer, 2, allowed), tokenizer("go left", add_special_tokens=False)["input_ids"]
    batch = vlm.encode(small_clips, QUESTIONS, ANSWERS)
    both, _ = splice_prefix(batch, prefix)
    both, starts = splice_suffix(both, suffix)
    n, m = len(prefix), len(suffix)
    for i, start in enumerate(starts):
        q_start, q_end = batch.question_spans[i]
        old, row = batch.inputs["input_ids"][i].tolist(), both.inputs["input_ids"][i].tolist()
        assert row[q_start:q_start + n] == prefix and start == q_end + n
        assert row[q_start + n:q_end + n] == old[q_start:q_end]  # the question between them, unchanged
        assert row[start:start + m] == suffix and row[start + m:] == old[q_end:]  # the rest of the turn after
        assert both.question_spans[i] == (q_start + n, q_end + n)
        assert both.labels[i, start:start + m].eq(IGNORE_INDEX).all()
        a_start, a_end = both.answer_spans[i]
        assert row[a_start:a_end] == old[batch.answer_spans[i][0]:batch.answer_spans[i][1]]
    # the objective scores a suffix control at that place, with the part's fixed prefix before the question
    objective = ControlObjective(vlm, {"attack": Part(Examples(small_clips, QUESTIONS, ANSWERS), 1.0,
                                                      prefix=prefix)}, "suffix")
    with torch.no_grad():
        direct = vlm.loss_from_embeds(both, vlm.embed(both)).mean().item()
    assert objective.loss(suffix) == pytest.approx(direct, rel=1e-5)
    value, gradient = objective.gradient(suffix)
    assert value == pytest.approx(direct, rel=1e-5) and gradient.shape[0] == m


def test_pat_alternates_attack_and_defense_and_resumes_where_it_stopped(tiny_hf_vlm, small_clips, tmp_path,
                                                                        monkeypatch):
    from lanevil_train.vlm.defenses import pat_baseline

    vlm = tiny_hf_vlm("qwen2_vl")
    attacked = Examples(small_clips, QUESTIONS, ANSWERS)
    wrong = ["Yes.", "A. Two lanes."]
    benign = Examples(small_clips[:1], ["Is it wet?"], ["No, the road is dry."])
    settings = dict(prefix_length=3, suffix_length=3, top_k=16, num_candidates=8, seed=2)
    whole = tune_pat(vlm, attacked, wrong, benign, PATSettings(steps=3, **settings), alpha=0.2, out_dir=tmp_path / "w",
                     chunk=8, progress="none", facts={"model": "tiny"})
    assert whole["step"] == 3 and len(whole["history"]) == 4 and len(whole["attack"]["history"]) == 4
    assert whole["facts"]["method"] == "pat" and len(whole["attack"]["ids"]) == 3
    # the losses recorded are the objectives' at the kept prefix and suffix
    suffix, prefix = whole["attack"]["ids"], whole["ids"]
    attack = ControlObjective(vlm, {"a": Part(Examples(small_clips, QUESTIONS, wrong), 1.0, prefix=prefix)}, "suffix")
    defense = ControlObjective(vlm, {"benign": Part(benign, 0.2), "attacked": Part(attacked, 0.8, suffix=suffix)})
    assert whole["attack"]["loss"] == pytest.approx(attack.loss(suffix), rel=1e-5)
    assert whole["loss"] == pytest.approx(defense.loss(prefix), rel=1e-5)
    assert whole["terms"] == pytest.approx(defense.terms(prefix), rel=1e-5)

    tune_pat(vlm, attacked, wrong, benign, PATSettings(steps=1, **settings), alpha=0.2, out_dir=tmp_path / "r",
             chunk=8, progress="none", facts={"model": "tiny"})
    steps = []
    real = pat_baseline.gcg_step
    monkeypatch.setattr(pat_baseline, "gcg_step", lambda *a, **k: steps.append(a[0].slot) or real(*a, **k))
    resumed = tune_pat(vlm, attacked, wrong, benign, PATSettings(steps=3, **settings), alpha=0.2,
                       out_dir=tmp_path / "r", chunk=8, progress="none", facts={"model": "tiny"})
    assert steps == ["suffix", "prefix"] * 2  # attack then defense, steps 2 and 3 only
    assert resumed["ids"] == whole["ids"] and resumed["attack"]["ids"] == whole["attack"]["ids"]
    assert resumed["history"] == pytest.approx(whole["history"], rel=1e-6)
    with pytest.raises(ValueError, match="tuned with alpha=0.2, this run has alpha=0.5"):
        tune_pat(vlm, attacked, wrong, benign, PATSettings(steps=4, **settings), alpha=0.5, out_dir=tmp_path / "r",
                 progress="none", facts={"model": "tiny"})
    with pytest.raises(ValueError, match="defense.suffix_length: expected a positive integer, got 0"):
        PATSettings(suffix_length=0)
