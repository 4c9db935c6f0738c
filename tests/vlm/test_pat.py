"""PAT++: the prefix's place in each family's ids, its loss and one-hot gradient checked by hand, GCG steps that never
raise the kept loss, allowed tokens only, and prefix.json."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lanevil_dev.tiny_vlm import FAMILIES
from lanevil_train.vlm.backends.hf import HFVLM, IGNORE_INDEX
from lanevil_train.vlm.defenses.gcg import (
    Examples,
    allowed_tokens,
    gcg_step,
    initial_prefix,
    retokenises,
    splice_prefix,
)
from lanevil_train.vlm.defenses.pat import RES_GOAL, PrefixObjective, hard_mask, hard_target, load_prefix, save_prefix

QUESTIONS = ["How many lanes does the road have in front of the ego vehicle?", "Is it wet?"]
ANSWERS = ["The road has three lanes.", "Yes."]


def _placeholder_ids(vlm: HFVLM) -> set[int]:
    tokens = {getattr(vlm.processor, name, None) for name in ("image_token", "video_token")} - {None}
    return {vlm.processor.tokenizer.convert_tokens_to_ids(token) for token in tokens}


def _prefix_for(vlm: HFVLM, length: int = 3) -> list[int]:
    tokenizer = vlm.processor.tokenizer
    return initial_prefix(tokenizer, length, allowed_tokens(tokenizer, vlm.model.get_input_embeddings().num_embeddings))


def _check_placement(vlm: HFVLM, clips, prefix, question_first: bool):
    batch = vlm.encode(clips, QUESTIONS, ANSWERS)
    spliced, starts = splice_prefix(batch, prefix)
    n, images = len(prefix), _placeholder_ids(vlm)
    for i, start in enumerate(starts):
        row = spliced.inputs["input_ids"][i].tolist()
        old = batch.inputs["input_ids"][i].tolist()
        q_start, q_end = batch.question_spans[i]
        assert start == q_start
        assert row[start:start + n] == prefix
        assert row[start + n:q_end + n] == old[q_start:q_end]  # the question follows the prefix unchanged
        assert spliced.question_spans[i] == (q_start + n, q_end + n)
        media = [k for k, token in enumerate(row) if token in images]
        assert media, "no image or video tokens found"
        if question_first:
            assert min(media) >= q_end + n  # prefix, question, then the video
        else:
            assert max(media) < start  # the frames, then prefix and question
        assert spliced.labels[i, start:start + n].eq(IGNORE_INDEX).all()
        a_start, a_end = spliced.answer_spans[i]
        assert spliced.labels[i, a_start:a_end].tolist() == row[a_start:a_end]
        assert int(spliced.inputs["attention_mask"][i, start:start + n].sum()) == n
    return spliced


@pytest.mark.parametrize("family", FAMILIES)
def test_the_prefix_sits_after_the_frames_and_before_the_question_in_each_family(family, tiny_hf_vlm, small_clips):
    vlm = tiny_hf_vlm(family)
    prefix = _prefix_for(vlm)
    spliced = _check_placement(vlm, small_clips, prefix, question_first=False)
    # the spliced ids are an ordinary prompt: the model runs on them and the loss from embeddings matches
    with torch.no_grad():
        nll = vlm.loss_from_embeds(spliced, vlm.embed(spliced))
    assert torch.isfinite(nll).all() and nll.shape == (2,)


def test_the_prefix_comes_before_the_question_and_so_the_video_in_the_embedded_vlm(tmp_path):
    from lanevil_train.vlm.backends.embedded import DEFAULT_FRAME_SIZE, build_embedded_vlm

    model_dir = build_embedded_vlm(tmp_path / "model", QUESTIONS + ANSWERS, seed=1)
    vlm = HFVLM(model_dir, dtype="float32", device="cpu")
    rng = np.random.default_rng(0)
    clips = [[rng.integers(0, 256, (*DEFAULT_FRAME_SIZE, 3), dtype=np.uint8) for _ in range(6)] for _ in range(2)]
    _check_placement(vlm, clips, _prefix_for(vlm), question_first=True)


def _hand_nll(vlm: HFVLM, clip, question: str, target: str, prefix: list[int]) -> float:
    """A sample's mean target NLL with the prefix inserted by hand into its own unpadded ids, the model given the
    ids (it places the image features and positions itself)."""
    batch = vlm.encode([clip], [question], [target])
    start = batch.question_spans[0][0]
    inputs = {}
    for key, value in batch.inputs.items():
        if torch.is_tensor(value) and not torch.is_floating_point(value) and value.shape == batch.inputs[
                "input_ids"].shape:
            fill = prefix if key == "input_ids" else [1 if key == "attention_mask" else 0] * len(prefix)
            values = value[0].tolist()
            inputs[key] = torch.tensor([values[:start] + fill + values[start:]])
        else:
            inputs[key] = value
    a_start, a_end = batch.answer_spans[0]
    a_start, a_end = a_start + len(prefix), a_end + len(prefix)
    with torch.no_grad():
        logits = vlm.model(**inputs, use_cache=False).logits[0].double()
    logp = torch.log_softmax(logits, dim=-1)
    ids = inputs["input_ids"][0]
    return float(-torch.stack([logp[t - 1, ids[t]] for t in range(a_start, a_end)]).mean())


@pytest.mark.parametrize("family", ["qwen2_vl", "llava"])
def test_the_loss_is_alpha_times_benign_plus_one_minus_alpha_times_hard_by_hand(family, tiny_hf_vlm, small_clips):
    vlm = tiny_hf_vlm(family)
    prefix = _prefix_for(vlm, 4)
    benign = Examples(small_clips, QUESTIONS, ANSWERS)
    hard = Examples(small_clips[::-1], QUESTIONS, [hard_target(a) for a in ANSWERS])
    objective = PrefixObjective(vlm, benign, hard, alpha=0.3)
    l_bgn = np.mean([_hand_nll(vlm, c, q, t, prefix) for c, q, t in zip(benign.clips, benign.questions,
                                                                          benign.targets)])
    l_hard = np.mean([_hand_nll(vlm, c, q, t, prefix) for c, q, t in zip(hard.clips, hard.questions, hard.targets)])
    assert objective.terms(prefix) == pytest.approx({"benign": l_bgn, "hard": l_hard}, rel=1e-4)
    assert objective.loss(prefix) == pytest.approx(0.3 * l_bgn + 0.7 * l_hard, rel=1e-4)
    other = prefix[:-1] + [prefix[0] + 1]
    assert objective.loss(other) != pytest.approx(objective.loss(prefix), rel=1e-6)  # the prefix matters
    # candidates scored two to a pass (the last pass padded) each get their own loss
    third = [prefix[1]] + prefix[1:]
    chunked = PrefixObjective(vlm, benign, hard, alpha=0.3, chunk=4)
    assert chunked.losses([prefix, other, third]).tolist() == pytest.approx(
        [objective.loss(prefix), objective.loss(other), objective.loss(third)], rel=1e-4)
    only_benign = PrefixObjective(vlm, benign, Examples([], [], []), alpha=0.3)
    assert only_benign.loss(prefix) == pytest.approx(l_bgn, rel=1e-4)


def test_the_one_hot_gradient_equals_a_finite_difference(tiny_vlm_dir, small_clips):
    vlm = HFVLM(tiny_vlm_dir("qwen2_vl"), dtype="float32", device="cpu")
    vlm.model.double()
    prefix = _prefix_for(vlm, 3)
    objective = PrefixObjective(vlm, Examples(small_clips, QUESTIONS, ANSWERS),
                                Examples(small_clips[:1], QUESTIONS[:1], [RES_GOAL]), alpha=0.6)
    loss, gradient = objective.gradient(prefix)
    assert loss == pytest.approx(objective.loss(prefix), rel=1e-9)
    table = vlm.model.get_input_embeddings().weight.detach()

    def loss_with(position: int, delta):
        total = 0.0
        for part, weight in objective.weights().items():
            spliced, starts = splice_prefix(objective._batch(part, 1), prefix)
            embeds = vlm.embed(spliced).detach().clone()
            for i, s in enumerate(starts):
                embeds[i, s + position] += delta
            with torch.no_grad():
                total += weight * float(vlm.loss_from_embeds(spliced, embeds).mean())
        return total

    # the model keeps some float32 inside (rotary tables), so the step is large enough to stand above that noise
    eps = 0.03
    for position, token in [(0, 5), (1, 100), (2, prefix[2]), (1, int(gradient[1].abs().argmax()))]:
        estimate = (loss_with(position, eps * table[token]) - loss_with(position, -eps * table[token])) / (2 * eps)
        assert float(gradient[position, token]) == pytest.approx(estimate, rel=5e-3)
        assert abs(estimate) > 1e-5


def test_gcg_steps_never_raise_the_kept_loss_and_use_allowed_tokens_only(tiny_hf_vlm, small_clips):
    vlm = tiny_hf_vlm("qwen2_vl")
    tokenizer = vlm.processor.tokenizer
    allowed = allowed_tokens(tokenizer, vlm.model.get_input_embeddings().num_embeddings)
    objective = PrefixObjective(vlm, Examples(small_clips, QUESTIONS, ANSWERS),
                                Examples(small_clips[:1], QUESTIONS[:1], [RES_GOAL]), alpha=0.6, chunk=16)
    prefix = initial_prefix(tokenizer, 4, allowed)
    losses = [objective.loss(prefix)]
    generator = torch.Generator().manual_seed(0)
    improved = 0
    for _ in range(3):
        step = gcg_step(objective, prefix, allowed, tokenizer, top_k=32, num_candidates=24, generator=generator)
        assert step.loss <= losses[-1] + 1e-9
        assert step.loss == pytest.approx(objective.loss(step.prefix), rel=1e-5)
        assert step.candidates > 0
        improved += step.improved
        prefix = step.prefix
        losses.append(step.loss)
    assert improved >= 1 and losses[-1] < losses[0]
    assert all(allowed[t] for t in prefix) and retokenises(tokenizer, prefix)
    assert not set(prefix) & set(tokenizer.all_special_ids)
    assert tokenizer.decode(prefix).isascii() and tokenizer.decode(prefix).isprintable()


def test_allowed_tokens_exclude_special_image_and_non_ascii_tokens(tiny_hf_vlm):
    vlm = tiny_hf_vlm("llava")
    tokenizer = vlm.processor.tokenizer
    allowed = allowed_tokens(tokenizer, vlm.model.get_input_embeddings().num_embeddings)
    for token in set(tokenizer.all_special_ids) | _placeholder_ids(vlm):
        assert not allowed[token]
    ascii_word = tokenizer("road", add_special_tokens=False)["input_ids"]
    assert all(allowed[t] for t in ascii_word)
    for token in torch.nonzero(allowed).flatten().tolist():
        text = tokenizer.decode([token])
        assert text.strip() and all(32 <= ord(ch) < 127 for ch in text)
    assert 0 < int(allowed.sum()) < len(tokenizer)
    assert tokenizer.decode(initial_prefix(tokenizer, 5, allowed)).replace(" ", "") == "!!!!!"


def test_hard_examples_are_those_below_the_mean_and_targets_follow_the_mode():
    assert hard_mask([1.0, 0.0, 0.5, 0.9]) == [False, True, True, False]  # mean 0.6
    assert hard_mask([0.5, 0.5]) == [False, False]
    assert hard_target("Yes. Two lanes.") == RES_GOAL
    assert hard_target("Yes. Two lanes.", "goal_then_answer") == f"{RES_GOAL}. Yes. Two lanes."
    with pytest.raises(ValueError, match="defense.hard_target: expected one of goal, goal_then_answer"):
        hard_target("x", "answer")
    with pytest.raises(ValueError, match="defense.alpha: expected a weight in"):
        PrefixObjective(None, Examples([], [], []), Examples([[0]], ["q"], ["a"]), alpha=1.5)


def test_prefix_json_round_trips_and_a_foreign_prefix_is_refused(tiny_hf_vlm, tmp_path):
    tokenizer = tiny_hf_vlm("qwen2_vl").processor.tokenizer
    ids = tokenizer("mind the road", add_special_tokens=False)["input_ids"]
    path = save_prefix(tmp_path / "run" / "prefix.json", ids, tokenizer, loss=1.25, step=7)
    record = load_prefix(path, tokenizer)
    assert record["ids"] == ids and record["text"] == "mind the road" and record["step"] == 7
    assert not list(path.parent.glob("*.partial"))
    bad = dict(record, text="something else")
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="decode to 'mind the road' with this model's tokenizer"):
        load_prefix(tmp_path / "bad.json", tokenizer)
    (tmp_path / "big.json").write_text(json.dumps(dict(record, ids=[len(tokenizer) + 3])))
    with pytest.raises(ValueError, match="outside this model's vocabulary"):
        load_prefix(tmp_path / "big.json", tokenizer)
    with pytest.raises(FileNotFoundError, match="defense.prefix_path: no prefix file at"):
        load_prefix(tmp_path / "missing.json")


def test_tuning_keeps_the_best_prefix_and_a_stopped_run_resumes_where_it_was(tiny_hf_vlm, small_clips, tmp_path,
                                                                              monkeypatch):
    from lanevil_train.vlm.defenses import pat
    from lanevil_train.vlm.defenses.pat import GCGSettings, tune_prefix

    vlm = tiny_hf_vlm("qwen2_vl")
    objective = PrefixObjective(vlm, Examples(small_clips, QUESTIONS, ANSWERS),
                                Examples(small_clips[:1], QUESTIONS[:1], [RES_GOAL]), alpha=0.6, chunk=16)
    settings = dict(prefix_length=3, top_k=16, num_candidates=12, seed=5)
    whole = tune_prefix(objective, GCGSettings(steps=4, **settings), tmp_path / "whole", progress="none",
                        facts={"model": "tiny"})
    assert whole["step"] == 4 and len(whole["history"]) == 5
    assert all(b <= a for a, b in zip(whole["history"], whole["history"][1:]))
    assert whole["loss"] == pytest.approx(objective.loss(whole["ids"]), rel=1e-5)
    assert whole["terms"]["benign"] * 0.6 + whole["terms"]["hard"] * 0.4 == pytest.approx(whole["loss"], rel=1e-5)

    tune_prefix(objective, GCGSettings(steps=2, **settings), tmp_path / "split", progress="none",
                facts={"model": "tiny"})
    calls = []
    monkeypatch.setattr(pat, "gcg_step", lambda *args, **kwargs: calls.append(1) or gcg_step(*args, **kwargs))
    resumed = tune_prefix(objective, GCGSettings(steps=4, **settings), tmp_path / "split", progress="none",
                          facts={"model": "tiny"})
    assert len(calls) == 2  # steps 3 and 4 only
    assert resumed["ids"] == whole["ids"] and resumed["history"] == pytest.approx(whole["history"])
    with pytest.raises(ValueError, match=r"tuned with top_k=16, this run has top_k=8"):
        tune_prefix(objective, GCGSettings(steps=5, **dict(settings, top_k=8)), tmp_path / "split", progress="none",
                    facts={"model": "tiny"})
    with pytest.raises(ValueError, match="defense.num_candidates: expected a positive integer, got 0"):
        GCGSettings(num_candidates=0)


@pytest.mark.parametrize("family", ["qwen2_vl", "idefics3"])
def test_a_prefixed_vlm_answers_and_scores_with_the_prefix_spliced_in(family, tiny_hf_vlm, small_clips):
    from lanevil_train.vlm.defenses.pat import PrefixedVLM

    vlm = tiny_hf_vlm(family)
    prefix = vlm.processor.tokenizer("keep to the lane", add_special_tokens=False)["input_ids"]
    defended = PrefixedVLM(vlm, prefix)
    spliced, _ = splice_prefix(vlm.encode(small_clips, QUESTIONS), prefix)
    with torch.no_grad():
        expected = vlm.generate_encoded(spliced)
    assert defended.answer(small_clips, QUESTIONS) == expected
    objective = PrefixObjective(vlm, Examples(small_clips, QUESTIONS, ANSWERS), Examples([], [], []))
    with torch.no_grad():
        assert defended.answer_loss(small_clips, QUESTIONS, ANSWERS).mean().item() == pytest.approx(
            objective.loss(prefix), rel=1e-5)
        without = vlm.answer_loss(small_clips, QUESTIONS, ANSWERS).mean().item()
        assert abs(without - objective.loss(prefix)) > 1e-5  # the prefix is there
    assert defended.identity()["defense_prefix_ids"] == prefix and defended.name == vlm.name
    assert "defense_prefix_ids" not in vlm.identity()
    with pytest.raises(ValueError, match=r"defense prefix: expected token ids in \[0, "):
        PrefixedVLM(vlm, [10 ** 9])


def test_a_soft_prefix_lowers_the_loss_keeps_its_best_vectors_and_resumes_exactly(tiny_hf_vlm, small_clips, tmp_path):
    from lanevil_train.vlm.defenses.pat import SoftSettings, tune_soft_prefix

    vlm = tiny_hf_vlm("qwen2_vl")
    objective = PrefixObjective(vlm, Examples(small_clips, QUESTIONS, ANSWERS),
                                Examples(small_clips[:1], QUESTIONS[:1], [RES_GOAL]), alpha=0.6)
    settings = dict(prefix_length=3, lr=0.05, seed=1)
    whole = tune_soft_prefix(objective, SoftSettings(steps=4, **settings), tmp_path / "whole", progress="none",
                             facts={"model": "tiny"})
    history = whole["history"]
    assert whole["soft"] is True and len(history) == 4 and history[-1] < history[0]
    assert whole["loss"] == pytest.approx(min(history)) and len(whole["embeddings"]) == 3
    vectors = torch.tensor(whole["embeddings"])
    with torch.no_grad():
        total, terms = objective.loss_with_embeds(whole["ids"], vectors)
    assert float(total) == pytest.approx(whole["loss"], rel=1e-5) and terms == pytest.approx(whole["terms"], rel=1e-5)
    # the ids are the placeholders "! ! !"; a run stopped after 2 steps ends where the unbroken one does
    assert vlm.processor.tokenizer.decode(whole["ids"]).replace(" ", "") == "!!!"
    tune_soft_prefix(objective, SoftSettings(steps=2, **settings), tmp_path / "split", progress="none",
                     facts={"model": "tiny"})
    resumed = tune_soft_prefix(objective, SoftSettings(steps=4, **settings), tmp_path / "split", progress="none",
                               facts={"model": "tiny"})
    assert resumed["history"] == pytest.approx(history, rel=1e-6)
    assert torch.allclose(torch.tensor(resumed["embeddings"]), vectors, atol=1e-6)
    with pytest.raises(ValueError, match="defense.soft_lr: expected a learning rate > 0"):
        SoftSettings(lr=0)


def test_a_prefixed_vlm_with_soft_vectors_embeds_them_in_the_prompt_pass_only(tiny_hf_vlm, small_clips):
    from lanevil_train.vlm.defenses.pat import PrefixedVLM

    vlm = tiny_hf_vlm("qwen2_vl")
    ids = _prefix_for(vlm, 3)
    vectors = torch.randn(3, vlm.model.get_input_embeddings().embedding_dim, generator=torch.Generator().manual_seed(0))
    soft = PrefixedVLM(vlm, ids, embeddings=vectors)
    objective = PrefixObjective(vlm, Examples(small_clips, QUESTIONS, ANSWERS), Examples([], [], []))
    with torch.no_grad():
        assert soft.answer_loss(small_clips, QUESTIONS, ANSWERS).mean().item() == pytest.approx(
            float(objective.loss_with_embeds(ids, vectors)[0]), rel=1e-5)
        assert soft.answer_loss(small_clips, QUESTIONS, ANSWERS).mean().item() != pytest.approx(
            PrefixedVLM(vlm, ids).answer_loss(small_clips, QUESTIONS, ANSWERS).mean().item(), rel=1e-4)
    seen = []  # what the decoder is given: the input embeddings, frames placed
    decoder = vlm.model.model.language_model
    handle = decoder.register_forward_pre_hook(lambda m, a, k: seen.append(k["inputs_embeds"].detach()),
                                               with_kwargs=True)
    try:
        answers = soft.answer(small_clips, QUESTIONS)
    finally:
        handle.remove()
    assert len(answers) == 2
    batch, starts = splice_prefix(vlm.encode(small_clips, QUESTIONS), ids)
    prompt = seen[0]
    assert prompt.shape[1] == batch.inputs["input_ids"].shape[1]
    for i, start in enumerate(starts):
        assert torch.allclose(prompt[i, start:start + 3], vectors)
    assert all(step.shape[1] == 1 for step in seen[1:])  # generation steps after the prompt: new tokens only
    assert len(vlm.model.get_input_embeddings()._forward_hooks) == 0  # nothing left on the wrapped model
    assert soft.identity()["defense_prefix_embeddings"] != PrefixedVLM(vlm, ids, embeddings=vectors + 1).identity()[
        "defense_prefix_embeddings"]
    with pytest.raises(ValueError, match=r"expected soft embeddings \[3, "):
        PrefixedVLM(vlm, ids, embeddings=vectors[:2])
