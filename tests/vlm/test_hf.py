"""The local Hugging Face backend on tiny random-weight models of every family, built offline."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from lanevil_dev.tiny_vlm import FAMILIES, make_tiny_vlm
from lanevil_train.vlm.backends.hf import HFVLM, IGNORE_INDEX, model_dir_hash

QUESTIONS = ["How many lanes does the road have in front of the ego vehicle?", "Is it wet?"]
ANSWERS = ["The road has three lanes.", "Yes."]


@pytest.mark.parametrize("family", FAMILIES)
def test_saved_tiny_model_loads_back_with_identical_logits(family, tiny_vlm_dir, small_clips):
    """The saved directory, read back through the Auto classes, computes what the in-memory model computes."""
    from transformers import AutoModelForImageTextToText, AutoProcessor

    path = tiny_vlm_dir(family)
    built, _ = make_tiny_vlm(family)
    processor = AutoProcessor.from_pretrained(path, local_files_only=True)
    loaded = AutoModelForImageTextToText.from_pretrained(path, local_files_only=True, dtype=torch.float32).eval()
    text = processor.apply_chat_template(
        [{"role": "user", "content": [{"type": "image"}] * 6 + [{"type": "text", "text": QUESTIONS[0]}]}],
        add_generation_prompt=True, tokenize=False)
    inputs = processor(text=[text], images=[small_clips[0]], return_tensors="pt")
    with torch.no_grad():
        expected, got = built(**inputs).logits, loaded(**inputs).logits
    assert got.shape[-1] == len(processor.tokenizer)
    assert torch.equal(expected, got)


@pytest.mark.parametrize("family", FAMILIES)
def test_answer_is_deterministic_and_left_padding_does_not_change_it(family, tiny_hf_vlm, small_clips):
    """Two clips give two strings, the same on a second call, and the same as each pair answered alone."""
    vlm = tiny_hf_vlm(family)
    together = vlm.answer(small_clips, QUESTIONS)
    assert len(together) == 2 and all(isinstance(text, str) for text in together)
    assert any(together), "the tiny model generated nothing at all"
    assert vlm.answer(small_clips, QUESTIONS) == together
    alone = [vlm.answer([clip], [question])[0] for clip, question in zip(small_clips, QUESTIONS)]
    assert alone == together


@pytest.mark.parametrize("family", FAMILIES)
def test_answer_loss_is_the_answer_tokens_nll_with_gradients_to_the_embeddings(family, tiny_hf_vlm, small_clips):
    """The batched loss of each sample equals the NLL of its answer tokens computed alone from the model's logits;
    the labels decode to the answer, the question span to the question, and the gradient reaches the embeddings."""
    vlm = tiny_hf_vlm(family)
    batch = vlm.encode(small_clips, QUESTIONS, ANSWERS)
    tokenizer = vlm.processor.tokenizer
    for i in range(2):
        labelled = batch.labels[i][batch.labels[i] != IGNORE_INDEX]
        assert tokenizer.decode(labelled).strip() == ANSWERS[i]
        start, end = batch.question_spans[i]
        assert tokenizer.decode(batch.inputs["input_ids"][i, start:end]).strip() == QUESTIONS[i]
    embeds = vlm.embed(batch).detach().requires_grad_()
    loss = vlm.loss_from_embeds(batch, embeds)
    assert loss.shape == (2,) and torch.isfinite(loss).all()
    loss.sum().backward()
    assert embeds.grad is not None and embeds.grad.abs().sum() > 0
    for i in range(2):
        assert loss[i].item() == pytest.approx(_manual_nll(vlm, small_clips[i], QUESTIONS[i], ANSWERS[i]), rel=1e-4)
    direct = vlm.answer_loss(small_clips, QUESTIONS, ANSWERS)
    assert direct.requires_grad and torch.allclose(direct, loss.detach(), rtol=1e-5)


def _manual_nll(vlm: HFVLM, clip, question: str, answer: str) -> float:
    """Mean NLL of the answer tokens of one unpadded sample, from the model's own forward on input ids."""
    single = vlm.encode([clip], [question], [answer])
    start, end = single.answer_spans[0]
    with torch.no_grad():
        logits = vlm.model(**single.inputs).logits[0].float()
    ids = single.inputs["input_ids"][0]
    log_probs = torch.log_softmax(logits[start - 1:end - 1], dim=-1)
    return -log_probs[torch.arange(end - start), ids[start:end]].mean().item()


@pytest.mark.parametrize("family", ["qwen2_vl", "llava_onevision"])
def test_video_families_also_take_the_frames_as_images(family, tiny_vlm_dir, small_clips):
    """frames_as='images' gives a video family six images: one image placeholder per frame, a finite loss."""
    vlm = HFVLM(tiny_vlm_dir(family), dtype="float32", device="cpu", max_new_tokens=2, frames_as="images")
    assert vlm.frames_as == "images"
    batch = vlm.encode(small_clips[:1], QUESTIONS[:1], ANSWERS[:1])
    assert "pixel_values" in batch.inputs and "pixel_values_videos" not in batch.inputs
    assert torch.isfinite(vlm.loss_from_embeds(batch, vlm.embed(batch))).all()
    assert len(vlm.answer(small_clips[:1], QUESTIONS[:1])) == 1


def test_auto_picks_video_for_qwen_and_images_for_llava(tiny_hf_vlm):
    """frames_as='auto' is a video where the family takes one natively, several images elsewhere."""
    assert tiny_hf_vlm("qwen2_5_vl").frames_as == "video"
    assert tiny_hf_vlm("llava").frames_as == "images"


def test_system_prompt_is_rendered_before_the_question(tiny_vlm_dir, small_clips):
    """The system prompt reaches the model's input text, ahead of the question."""
    vlm = HFVLM(tiny_vlm_dir("qwen2_vl"), device="cpu", system_prompt="Drive safely.")
    text, q_span, _ = vlm._render(small_clips[0], "Is it wet?", None)
    assert "Drive safely." in text and text.index("Drive safely.") < q_span[0]
    assert text[q_span[0]:q_span[1]] == "Is it wet?"


def test_identity_names_the_model_and_the_generation_settings(tiny_vlm_dir, tiny_hf_vlm):
    """identity() changes with the weights' fingerprint and with settings that change answers."""
    path = tiny_vlm_dir("llava")
    identity = tiny_hf_vlm("llava").identity()
    assert identity["path"] == str(path.resolve()) and identity["max_new_tokens"] == 4
    assert identity["frames_as"] == "images" and identity["dtype"] == "float32"
    assert identity["model_hash"] == model_dir_hash(path) != model_dir_hash(tiny_vlm_dir("idefics3"))
    other = HFVLM(path, dtype="float32", device="cpu", max_new_tokens=5).identity()
    assert other != identity and json.loads(json.dumps(identity)) == identity


def test_refuses_a_path_that_is_not_a_model(tmp_path):
    """A missing path, an empty directory and a text-only architecture are named with what was expected."""
    with pytest.raises(FileNotFoundError, match="not a directory"):
        HFVLM(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match="no config.json"):
        HFVLM(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"model_type": "bert"}))
    with pytest.raises(ValueError, match="'bert' is not an image-text-to-text"):
        HFVLM(tmp_path)


def test_refuses_a_model_without_its_processor(tiny_vlm_dir, tmp_path):
    """Weights and config without processor or tokenizer files: the error says the processor is missing."""
    source = tiny_vlm_dir("llava")
    for name in ("config.json", "model.safetensors", "generation_config.json"):
        shutil.copy(source / name, tmp_path / name)
    with pytest.raises(FileNotFoundError, match="processor at"):
        HFVLM(tmp_path, device="cpu")


def test_refuses_bad_frames_and_bad_settings(tiny_hf_vlm, tiny_vlm_dir, small_clips):
    """Float frames, a missing clip and settings outside their choices are refused by name."""
    vlm = tiny_hf_vlm("llava")
    float_clip = [frame.astype(np.float32) for frame in small_clips[0]]
    with pytest.raises(ValueError, match="clip 0: frame 0 must be a uint8"):
        vlm.answer([float_clip], ["Is it wet?"])
    with pytest.raises(ValueError, match="1 clips for 2 questions"):
        vlm.answer_loss(small_clips[:1], QUESTIONS, ANSWERS)
    with pytest.raises(ValueError, match="answer 0: empty"):
        vlm.answer_loss(small_clips[:1], QUESTIONS[:1], ["   "])
    with pytest.raises(ValueError, match="frames_as: 'video'"):
        HFVLM(tiny_vlm_dir("llava"), device="cpu", frames_as="video")
    with pytest.raises(ValueError, match="dtype: expected one of"):
        HFVLM(tiny_vlm_dir("llava"), dtype="float64")
    with pytest.raises(ValueError, match="batch_size: expected an integer >= 1"):
        HFVLM(tiny_vlm_dir("llava"), batch_size=0)
