"""The embedded VLM: built offline, reloads through the Auto classes unchanged, answers through HFVLM, learns."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lanevil_train.vlm.backends.embedded import (
    DEFAULT_FRAME_SIZE,
    PARAMETER_RANGE,
    build_embedded_vlm,
    check_frame_size,
    check_sizes,
    count_parameters,
    fit_answers,
    make_embedded_vlm,
    pretrain_vision,
    qa_corpus,
    vision_tokens,
)
from lanevil_train.vlm.backends.hf import HFVLM
from lanevil_train.vlm.clips.qa_records import prompt_text

QAS = [
    {"type": "yes_no", "question": "Is the road surface wet?", "answer": "No. The road surface is dry."},
    {"type": "choice", "question": "How many lanes does this road have?",
     "choices": ["A. Two lanes.", "B. Three lanes.", "C. Four lanes.", "D. Five lanes."], "answer": "C. Four lanes."},
    {"type": "open", "question": "Describe the weather and lighting in this clip.",
     "answer": "It is sunset, with low, warm sunlight. The road surface is dry."},
    {"type": "yes_no", "question": "Is it night-time in this scene?", "answer": "Yes. It is night; the road is lit "
                                                                             "only by lamps and headlights."},
]


def _clip(seed: int, size=DEFAULT_FRAME_SIZE) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (*size, 3), dtype=np.uint8) for _ in range(6)]


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    return build_embedded_vlm(tmp_path_factory.mktemp("embedded") / "model", qa_corpus(QAS), seed=3)


def test_reloads_through_auto_classes_with_identical_logits(model_dir):
    from transformers import AutoModelForImageTextToText, AutoProcessor

    built, _ = make_embedded_vlm(qa_corpus(QAS), seed=3)
    loaded = AutoModelForImageTextToText.from_pretrained(model_dir, local_files_only=True).eval()
    processor = AutoProcessor.from_pretrained(model_dir, local_files_only=True)
    assert type(loaded).__name__ == "Qwen2VLForConditionalGeneration"
    messages = [{"role": "user", "content": [{"type": "video"}, {"type": "text", "text": QAS[0]["question"]}]}]
    text = processor.apply_chat_template(messages, add_generation_prompt=True, tokenize=False)
    inputs = processor(text=[text], videos=[np.stack(_clip(0))], return_tensors="pt")
    assert tuple(inputs["video_grid_thw"][0].tolist()) == (3, 8, 14)  # 6 frames of 64x112: 3 x 4 x 7 = 84 tokens
    assert int((inputs["input_ids"] == loaded.config.video_token_id).sum()) == 84
    with torch.no_grad():
        reloaded_logits = loaded(**inputs).logits
        built_logits = built.eval()(**inputs).logits
    assert torch.equal(reloaded_logits, built_logits)
    assert reloaded_logits.shape[-1] == len(processor.tokenizer)


def test_hfvlm_answers_and_scores_with_it(model_dir):
    vlm = HFVLM(model_dir, max_new_tokens=4, batch_size=2, device="cpu")
    assert vlm.frames_as == "video"
    answers = vlm.answer([_clip(0), _clip(1), _clip(2)], [prompt_text(qa) for qa in QAS[:3]])
    assert len(answers) == 3 and all(isinstance(a, str) for a in answers)
    loss = vlm.answer_loss([_clip(0)], [QAS[0]["question"]], [QAS[0]["answer"]])
    assert loss.shape == (1,) and 3.0 < float(loss.detach()) < 12.0  # random weights: about ln(vocab) = 6.9


def test_question_comes_before_the_video_so_answers_meet_every_vision_token_at_a_fixed_offset(model_dir):
    """The embedded template puts the question before the video: the encoded spans still decode to the question and
    the answer, and an answer token's M-RoPE distance to each vision token is the same for a short and a long
    question, which is what lets the decoder learn where on the frame to look."""
    vlm = HFVLM(model_dir, device="cpu")
    questions = ["Is the road wet?", prompt_text(QAS[1])]
    batch = vlm.encode([_clip(0), _clip(1)], questions, ["No.", "C. Four lanes."])
    tokenizer, ids = vlm.processor.tokenizer, batch.inputs["input_ids"]
    video = vlm.model.config.video_token_id
    positions = vlm.position_ids(batch)  # [3 (time, height, width), B, T]
    offsets = []
    for i in range(2):
        start, end = batch.question_spans[i]
        assert tokenizer.decode(ids[i, start:end]).strip() == questions[i]
        vision = (ids[i] == video).nonzero().flatten()
        assert end <= int(vision[0])  # the question, then the 84 video tokens
        a_start, a_end = batch.answer_spans[i]
        assert tokenizer.decode(ids[i, a_start:a_end]).strip() == ["No.", "C. Four lanes."][i]
        offsets.append(positions[:, i, a_start:a_start + 1] - positions[:, i, vision])
    assert torch.equal(offsets[0], offsets[1]) and len(set(offsets[0][2].tolist())) == 7  # 7 columns, fixed offsets


def test_decoder_rope_turns_far_enough_to_tell_columns_and_rows_apart(model_dir):
    """M-RoPE of the saved config: width gets the most rotary pairs, and its fastest one turns a column by well
    over a tenth of a radian (Qwen's 10000 base gave 0.003); time, 3 steps a clip, gets the fewest."""
    from transformers import AutoConfig

    rope = AutoConfig.from_pretrained(model_dir, local_files_only=True).text_config.rope_parameters
    time, height, width = rope["mrope_section"]
    assert (time, height, width) == (2, 4, 10) and time + height + width == 128 // 4 // 2
    inverse = [rope["rope_theta"] ** (-2 * k / 32) for k in range(16)]
    assert inverse[time + height] > 0.4 and inverse[-1] > 0.1  # width: every pair turns > 0.1 rad a column
    assert min(inverse[time:time + height]) > 0.4  # height: every pair turns > 0.4 rad a row


def test_tokenizer_covers_the_qa_corpus_without_unknown_bytes(model_dir):
    from transformers import AutoProcessor

    tokenizer = AutoProcessor.from_pretrained(model_dir, local_files_only=True).tokenizer
    for text in qa_corpus(QAS) + ["Unseen words: zebra crossing, 42 km/h, Ünïcode °"]:
        ids = tokenizer(text)["input_ids"]
        assert tokenizer.unk_token_id is None or tokenizer.unk_token_id not in ids
        assert tokenizer.decode(ids) == text
    # trained on the corpus: its frequent words are single tokens, so a question is short
    assert len(tokenizer("Is the road surface wet?")["input_ids"]) <= 8


def test_parameter_count_in_documented_range(model_dir):
    from transformers import AutoModelForImageTextToText

    model = AutoModelForImageTextToText.from_pretrained(model_dir, local_files_only=True)
    assert PARAMETER_RANGE[0] <= count_parameters(model) <= PARAMETER_RANGE[1]


def test_training_steps_reduce_the_answer_loss_on_a_fixed_batch(model_dir):
    vlm = HFVLM(model_dir, device="cpu")
    clips, questions, answers = [_clip(i) for i in range(4)], [prompt_text(qa) for qa in QAS], [
        qa["answer"] for qa in QAS]
    torch.manual_seed(0)
    losses = fit_answers(vlm, lambda step: (clips, questions, answers), steps=12, lr=3e-3, warmup=2)
    assert len(losses) == 12
    assert losses[-1] < 0.6 * losses[0], losses


def test_vision_pretraining_teaches_the_tower_the_scene_classes_and_leaves_the_decoder_alone(model_dir):
    """pretrain_vision trains the tower (its probe's loss falls on a fixed batch) and nothing else: the decoder, the
    embeddings and the head keep their weights, so the saved model is the same Qwen2-VL with a trained tower."""
    from lanevil_train.vlm.clips.qa import SCENE_CLASSES

    vlm = HFVLM(model_dir, device="cpu")
    before = {name: p.detach().clone() for name, p in vlm.model.named_parameters()}
    clips = [_clip(i) for i in range(4)]
    rng = np.random.default_rng(0)
    classes = [[int(rng.integers(len(v))) for v in SCENE_CLASSES.values()] for _ in clips]
    for row in classes:  # an ego lane on the road (mirroring needs it)
        row[1] = row[1] % SCENE_CLASSES["num_lanes"][row[0]]
    assert vision_tokens(vlm.model, vlm.processor, clips).shape == (4, 84, vlm.model.config.text_config.hidden_size)
    torch.manual_seed(0)
    losses = pretrain_vision(vlm.model, vlm.processor, lambda step: (clips, classes), steps=15, lr=3e-3,
                             progress="none", mirror=False)
    assert len(losses) == 15 and losses[-1] < 0.5 * losses[0], losses
    changed = {name for name, p in vlm.model.named_parameters() if not torch.equal(p, before[name])}
    assert changed and all(name.startswith("model.visual.") for name in changed), sorted(changed)
    assert any(".blocks." in name for name in changed) and any(".merger." in name for name in changed)
    mirrored = pretrain_vision(vlm.model, vlm.processor, lambda step: (clips, classes), steps=3, progress="none")
    assert len(mirrored) == 3 and all(np.isfinite(mirrored))
    with pytest.raises(ValueError, match=r"classes of shape \(4, 9\)"):
        pretrain_vision(vlm.model, vlm.processor, lambda step: (clips, [[0, 1]] * 4), steps=1, progress="none")


def test_mirrored_batch_flips_the_chosen_clips_and_mirrors_their_classes():
    from lanevil_train.vlm.backends.embedded import mirrored_batch
    from lanevil_train.vlm.clips.qa import mirror_scene_classes

    clips = [_clip(0), _clip(1)]
    classes = [[1, 0, 1, 0, 0, 0, 0, 1, 0], [0, 1, 2, 1, 1, 1, 1, 0, 2]]
    flipped, mirrored = mirrored_batch(clips, classes, [True, False])
    assert all(np.array_equal(f, frame[:, ::-1]) for f, frame in zip(flipped[0], clips[0]))
    assert flipped[1] is clips[1] and mirrored == [mirror_scene_classes(classes[0]), classes[1]]
    assert mirrored[0][1] == 2 and mirrored[0][8] == 2  # 3 lanes: ego lane 0 -> 2; bend left -> right


def test_bad_arguments_are_refused_naming_them(tmp_path, model_dir):
    with pytest.raises(ValueError, match="frame_size"):
        check_frame_size((60, 112))
    with pytest.raises(ValueError, match="size.hidden"):
        check_sizes({"hidden": 100})
    with pytest.raises(ValueError, match="a multiple of 16"):  # 4 heads of 24: too few rotary pairs to share out
        check_sizes({"hidden": 96})
    with pytest.raises(ValueError, match="unknown keys"):
        check_sizes({"width": 64})
    with pytest.raises(ValueError, match="corpus"):
        make_embedded_vlm("a string, not a list of texts")
    with pytest.raises(FileExistsError, match="out_dir"):
        build_embedded_vlm(model_dir, qa_corpus(QAS))
    with pytest.raises(ValueError, match=r"qas\[0\]"):
        qa_corpus([{"question": "no answer"}])
