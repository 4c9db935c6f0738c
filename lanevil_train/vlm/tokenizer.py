"""Byte-level BPE tokenizers trained here, offline, with a Hugging Face VLM family's special tokens.

The embedded VLM (backends/embedded.py) trains its vocabulary with `train_tokenizer` on its QA corpus; the tiny
random-weight test models of a source checkout (lanevil_dev/tiny_vlm.py) build on the same functions. Nothing is
downloaded: the tokenizer is trained on BASE_CORPUS (a small driving-QA text) plus the corpus given, so any text
still encodes (byte fallback).
"""

from __future__ import annotations

from typing import Sequence

FAMILIES = ("llava", "llava_onevision", "qwen2_vl", "qwen2_5_vl", "idefics3", "smolvlm")

VOCAB_SIZE = 640

BASE_CORPUS = (
    "How many lanes does the road have? The road has three lanes.",
    "Is the dark straight line in the left lane a lane marking? No, it is the shadow of a pole.",
    "What colour is the marking on the right of the ego lane? It is a solid white line.",
    "Which lane is the ego vehicle in? The ego vehicle is in the middle lane.",
    "Is there a crack in the road surface ahead? Yes, a long crack crosses the lane.",
    "What should the ego vehicle do next? Keep the lane and keep a safe distance.",
    "Describe the scene. A sunny highway with light traffic and a truck ahead.",
    "Is the car in front moving or stopped? The car in front is moving slowly.",
    "Does the lane marking continue after the repair patch? Yes, the dashed line continues.",
    "What is the weather? It is cloudy and the road is wet after rain.",
    "A. Turn left B. Keep lane C. Stop D. Change to the right lane. The answer is B.",
    "Frame 1 2 3 4 5 6 before over alongside the illusion; yes no maybe 0 1 2 3 4 5 6 7 8 9.",
)

# The family's special tokens (image/video placeholders, turn markers) and which of them play bos/eos/pad.
SPECIALS = {
    "llava": dict(tokens=["<s>", "</s>", "<pad>", "<image>"], bos="<s>", eos="</s>", pad="<pad>"),
    "llava_onevision": dict(tokens=["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<image>", "<video>"],
                            bos=None, eos="<|im_end|>", pad="<|endoftext|>"),
    "qwen2_vl": dict(tokens=["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>",
                             "<|image_pad|>", "<|video_pad|>"], bos=None, eos="<|im_end|>", pad="<|endoftext|>"),
    "idefics3": dict(tokens=["<|begin_of_text|>", "<|end_of_text|>", "<pad>", "<image>", "<fake_token_around_image>",
                             "<global-img>", "<end_of_utterance>"]
                     + [f"<row_{r}_col_{c}>" for r in range(1, 7) for c in range(1, 7)],
                     bos="<|begin_of_text|>", eos="<end_of_utterance>", pad="<pad>"),
}
SPECIALS["qwen2_5_vl"] = SPECIALS["qwen2_vl"]
SPECIALS["smolvlm"] = SPECIALS["idefics3"]


def family_spec(family: str) -> dict:
    """The special-token spec of `family`, else a ValueError listing the known families."""
    if family not in FAMILIES:
        raise ValueError(f"family: expected one of {', '.join(FAMILIES)}, got {family!r}")
    return SPECIALS[family]


def train_tokenizer(family: str, corpus: Sequence[str] = (), vocab_size: int = VOCAB_SIZE):
    """A byte-level BPE tokenizer of `vocab_size` ids trained here on driving QA text (+ `corpus`) with `family`'s
    special tokens."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors, trainers
    from transformers import PreTrainedTokenizerFast

    spec = family_spec(family)
    core = Tokenizer(models.BPE())
    core.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    core.decoder = decoders.ByteLevel()
    core.post_processor = processors.ByteLevel(trim_offsets=False)
    trainer = trainers.BpeTrainer(vocab_size=vocab_size, special_tokens=list(spec["tokens"]), show_progress=False,
                                  initial_alphabet=pre_tokenizers.ByteLevel.alphabet())
    core.train_from_iterator(list(BASE_CORPUS) + [str(text) for text in corpus], trainer)
    roles = {name: spec[name] for name in ("bos", "eos", "pad") if spec[name] is not None}
    return PreTrainedTokenizerFast(tokenizer_object=core, **{f"{k}_token": v for k, v in roles.items()},
                                   additional_special_tokens=[t for t in spec["tokens"] if t not in roles.values()])


def token_roles(tokenizer) -> dict:
    """bos/eos/pad token ids of `tokenizer` under the config's names (a None id is left out)."""
    roles = {"bos_token_id": tokenizer.bos_token_id, "eos_token_id": tokenizer.eos_token_id,
             "pad_token_id": tokenizer.pad_token_id}
    return {key: value for key, value in roles.items() if value is not None}


def qwen_ids(tokenizer) -> dict:
    """The Qwen configs' placeholder and vision-bracket token ids from `tokenizer`."""
    ids = tokenizer.convert_tokens_to_ids
    return dict(image_token_id=ids("<|image_pad|>"), video_token_id=ids("<|video_pad|>"),
                vision_start_token_id=ids("<|vision_start|>"), vision_end_token_id=ids("<|vision_end|>"))
