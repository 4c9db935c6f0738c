"""Tiny random-weight vision-language models of each Hugging Face family, built offline.

Nothing is downloaded: a byte-level BPE tokenizer is trained on a small driving-QA corpus with the family's
special tokens (lanevil_train/vlm/tokenizer.py, as the embedded VLM's is), the family's processor (image/video
processor + tokenizer + a chat template in the family's layout) is built around it, and a model with hidden size
32, 2 layers and a tiny vision tower is made from the family's config classes with its image/video/bos/eos/pad ids
taken from that tokenizer. Everything is saved with `save_pretrained`, so the directory loads back through
AutoProcessor + AutoModelForImageTextToText like a real checkpoint: tests, benchmarks and users smoke-testing a
setup from a source checkout (`model=vlm/hf model.path=DIR`) build on it. A test double: it lives in lanevil_dev/,
not in the wheel.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Sequence

from lanevil_train.vlm.tokenizer import FAMILIES, family_spec, qwen_ids, token_roles, train_tokenizer

__all__ = ["FAMILIES", "HIDDEN", "build_tiny_vlm", "make_tiny_vlm", "train_tokenizer"]

HIDDEN = 32

# Chat templates in each family's published layout (images first in the user turn, then the text).
_LLAVA_TEMPLATE = (
    "{% for message in messages %}{% if message['role'] != 'system' %}{{ message['role'].upper() + ': ' }}"
    "{% endif %}{% for c in message['content'] | selectattr('type', 'equalto', 'image') %}{{ '<image>\n' }}"
    "{% endfor %}{% for c in message['content'] | selectattr('type', 'equalto', 'text') %}{{ c['text'] + ' ' }}"
    "{% endfor %}{% endfor %}{% if add_generation_prompt %}{{ 'ASSISTANT:' }}{% endif %}")
_ONEVISION_TEMPLATE = (
    "{% for message in messages %}{{ '<|im_start|>' + message['role'] + ' ' }}"
    "{% for c in message['content'] | selectattr('type', 'equalto', 'image') %}{{ '<image>' }}{% endfor %}"
    "{% for c in message['content'] | selectattr('type', 'equalto', 'video') %}{{ '<video>' }}{% endfor %}"
    "{% for c in message['content'] | selectattr('type', 'equalto', 'text') %}{{ '\n' + c['text'] }}{% endfor %}"
    "{{ '<|im_end|>\n' }}{% endfor %}{% if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}{% endif %}")
_QWEN_TEMPLATE = (
    "{% for message in messages %}{% if loop.first and message['role'] != 'system' %}"
    "{{ '<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n' }}{% endif %}"
    "{{ '<|im_start|>' + message['role'] + '\n' }}{% for c in message['content'] %}"
    "{% if c['type'] == 'image' %}{{ '<|vision_start|><|image_pad|><|vision_end|>' }}"
    "{% elif c['type'] == 'video' %}{{ '<|vision_start|><|video_pad|><|vision_end|>' }}"
    "{% elif c['type'] == 'text' %}{{ c['text'] }}{% endif %}{% endfor %}{{ '<|im_end|>\n' }}{% endfor %}"
    "{% if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}{% endif %}")
_IDEFICS_TEMPLATE = (
    "<|begin_of_text|>{% for message in messages %}{{ message['role'] | capitalize }}"
    "{% if message['content'][0]['type'] == 'image' %}{{ ':' }}{% else %}{{ ': ' }}{% endif %}"
    "{% for c in message['content'] %}{% if c['type'] == 'text' %}{{ c['text'] }}"
    "{% elif c['type'] == 'image' %}{{ '<image>' }}{% endif %}{% endfor %}<end_of_utterance>\n{% endfor %}"
    "{% if add_generation_prompt %}{{ 'Assistant:' }}{% endif %}")
_TEMPLATES = {"llava": _LLAVA_TEMPLATE, "llava_onevision": _ONEVISION_TEMPLATE, "qwen2_vl": _QWEN_TEMPLATE,
              "qwen2_5_vl": _QWEN_TEMPLATE, "idefics3": _IDEFICS_TEMPLATE, "smolvlm": _IDEFICS_TEMPLATE}
_DEFAULT_IMAGE_SIZE = {"llava": 16, "llava_onevision": 16, "qwen2_vl": 32, "qwen2_5_vl": 32, "idefics3": 16,
                       "smolvlm": 16}


def make_tiny_vlm(family: str, corpus: Sequence[str] = (), seed: int = 0, image_size: int | None = None):
    """(model, processor) of a tiny random-weight `family` VLM in memory; the same seed gives the same weights."""
    import torch
    from transformers import AutoModelForImageTextToText, GenerationConfig

    family_spec(family)
    size = _DEFAULT_IMAGE_SIZE[family] if image_size is None else image_size
    if isinstance(size, bool) or not isinstance(size, int) or size < 8 or size % 8:
        raise ValueError(f"image_size: expected a multiple of 8 that is at least 8, got {image_size!r}")
    tokenizer = train_tokenizer(family, corpus)
    processor = _BUILDERS[family][0](tokenizer, size)
    config = _BUILDERS[family][1](tokenizer, size)
    torch.manual_seed(seed)
    model = AutoModelForImageTextToText.from_config(config).eval()
    model.generation_config = GenerationConfig(**token_roles(tokenizer))
    return model, processor


def build_tiny_vlm(family: str, out_dir: str | os.PathLike, corpus: Sequence[str] = (), seed: int = 0,
                   image_size: int | None = None) -> Path:
    """Build, save and return `out_dir`: a random-weight `family` model, its processor and tokenizer, offline."""
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"out_dir {out}: exists and is not empty; expected a new or empty directory")
    model, processor = make_tiny_vlm(family, corpus, seed, image_size)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:  # saved whole into a staging folder, then renamed: a kill never leaves a half-saved model at out_dir
        model.save_pretrained(staging)
        processor.save_pretrained(staging)
        if out.exists():
            out.rmdir()
        os.replace(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out


def _text_config(tokenizer, model_type: str, **extra) -> dict:
    """A 2-layer, hidden-32 decoder config dict of `model_type` sized to `tokenizer`."""
    return dict(model_type=model_type, vocab_size=len(tokenizer), hidden_size=HIDDEN, intermediate_size=64,
                num_hidden_layers=2, num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=4096,
                bos_token_id=tokenizer.bos_token_id, eos_token_id=tokenizer.eos_token_id,
                pad_token_id=tokenizer.pad_token_id, **extra)


def _vision_tower(model_type: str, size: int, patch: int) -> dict:
    """A 2-layer, hidden-32 ViT config dict of `model_type` for `size`-pixel square inputs."""
    return dict(model_type=model_type, hidden_size=HIDDEN, intermediate_size=64, num_hidden_layers=2,
                num_attention_heads=4, image_size=size, patch_size=patch)


def _llava_processor(tokenizer, size: int):
    """LLaVA: a CLIP image processor (shortest edge + centre crop to `size`), one `<image>` per frame."""
    from transformers import LlavaImageProcessor, LlavaProcessor
    images = LlavaImageProcessor(size={"shortest_edge": size}, crop_size={"height": size, "width": size})
    return LlavaProcessor(images, tokenizer, patch_size=size // 4, vision_feature_select_strategy="default",
                          num_additional_image_tokens=1, chat_template=_TEMPLATES["llava"])


def _llava_config(tokenizer, size: int):
    """LLaVA: CLIP vision tower (4x4 patches + CLS) and a Llama decoder."""
    from transformers import LlavaConfig
    vision = dict(_vision_tower("clip_vision_model", size, size // 4), projection_dim=HIDDEN)
    return LlavaConfig(vision_config=vision, text_config=_text_config(tokenizer, "llama"),
                       image_token_index=tokenizer.convert_tokens_to_ids("<image>"), image_seq_length=16,
                       vision_feature_select_strategy="default", vision_feature_layer=-1, **token_roles(tokenizer))


def _onevision_processor(tokenizer, size: int):
    """LLaVA-OneVision: SigLIP-style image and video processors, `<image>`/`<video>` placeholders."""
    from transformers import LlavaOnevisionImageProcessor, LlavaOnevisionProcessor, LlavaOnevisionVideoProcessor
    square = {"height": size, "width": size}
    images = LlavaOnevisionImageProcessor(size=square, image_grid_pinpoints=_onevision_pinpoints(size))
    videos = LlavaOnevisionVideoProcessor(size=square)
    return LlavaOnevisionProcessor(images, tokenizer, videos, num_image_tokens=16,
                                   vision_feature_select_strategy="full", chat_template=_TEMPLATES["llava_onevision"],
                                   vision_aspect_ratio="anyres_max_9")


def _onevision_pinpoints(size: int) -> list[list[int]]:
    """The any-resolution grid: 1x1, 1x2, 2x1 and 2x2 tiles of `size`."""
    return [[size, size], [size, 2 * size], [2 * size, size], [2 * size, 2 * size]]


def _onevision_config(tokenizer, size: int):
    """LLaVA-OneVision: SigLIP vision tower (4x4 patches) and a Qwen2 decoder."""
    from transformers import LlavaOnevisionConfig
    return LlavaOnevisionConfig(
        vision_config=_vision_tower("siglip_vision_model", size, size // 4),
        text_config=_text_config(tokenizer, "qwen2"), image_token_index=tokenizer.convert_tokens_to_ids("<image>"),
        video_token_index=tokenizer.convert_tokens_to_ids("<video>"), vision_feature_select_strategy="full",
        vision_feature_layer=-1, image_grid_pinpoints=_onevision_pinpoints(size), **token_roles(tokenizer))


def _qwen_processor(tokenizer, size: int, family: str):
    """Qwen2-VL / Qwen2.5-VL: patch-4 image and video processors with at most `size`x`size` pixels per frame."""
    from transformers import Qwen2VLImageProcessor, Qwen2VLVideoProcessor
    pixels = {"size": {"shortest_edge": 8 * 8, "longest_edge": size * size}, "patch_size": 4,
              "temporal_patch_size": 2, "merge_size": 2}
    images, videos = Qwen2VLImageProcessor(**pixels), Qwen2VLVideoProcessor(**pixels, cap_pixels_per_frame=True)
    if family == "qwen2_vl":
        from transformers import Qwen2VLProcessor as Processor
    else:
        from transformers import Qwen2_5_VLProcessor as Processor
    return Processor(images, tokenizer, videos, chat_template=_TEMPLATES[family])


def _qwen2_vl_config(tokenizer, size: int):
    """Qwen2-VL: a 2-block vision transformer (patch 4, merge 2) and an M-RoPE Qwen2 decoder."""
    from transformers import Qwen2VLConfig
    vision = dict(depth=2, embed_dim=HIDDEN, hidden_size=HIDDEN, num_heads=4, mlp_ratio=2, patch_size=4,
                  spatial_merge_size=2, temporal_patch_size=2)
    text = _text_config(tokenizer, "qwen2_vl_text", rope_parameters={"rope_type": "mrope", "mrope_section": [2, 1, 1]})
    return Qwen2VLConfig(vision_config=vision, text_config=text, **qwen_ids(tokenizer), **token_roles(tokenizer))


def _qwen2_5_vl_config(tokenizer, size: int):
    """Qwen2.5-VL: a 2-block windowed vision transformer (patch 4, merge 2) and an M-RoPE Qwen2 decoder."""
    from transformers import Qwen2_5_VLConfig
    vision = dict(depth=2, hidden_size=HIDDEN, out_hidden_size=HIDDEN, intermediate_size=64, num_heads=4,
                  patch_size=4, spatial_merge_size=2, temporal_patch_size=2, window_size=16,
                  fullatt_block_indexes=[1])
    text = _text_config(tokenizer, "qwen2_5_vl_text",
                        rope_parameters={"rope_type": "mrope", "mrope_section": [2, 1, 1]})
    return Qwen2_5_VLConfig(vision_config=vision, text_config=text, **qwen_ids(tokenizer), **token_roles(tokenizer))


def _idefics_processor(tokenizer, size: int, family: str):
    """Idefics3 / SmolVLM: one unsplit `size`-pixel tile per frame, `image_seq_len` tokens after pixel shuffle."""
    seq_len = (size // (size // 4)) ** 2 // 4
    resize = {"size": {"longest_edge": size}, "max_image_size": {"longest_edge": size}, "do_image_splitting": False}
    if family == "idefics3":
        from transformers import Idefics3ImageProcessor, Idefics3Processor
        return Idefics3Processor(Idefics3ImageProcessor(**resize), tokenizer, image_seq_len=seq_len,
                                 chat_template=_TEMPLATES[family])
    from transformers import SmolVLMImageProcessor, SmolVLMProcessor, SmolVLMVideoProcessor
    videos = SmolVLMVideoProcessor(**resize)
    return SmolVLMProcessor(SmolVLMImageProcessor(**resize), tokenizer, videos, image_seq_len=seq_len,
                            chat_template=_TEMPLATES[family])


def _idefics_config(tokenizer, size: int, family: str):
    """Idefics3 / SmolVLM: a SigLIP-style vision tower (4x4 patches, pixel shuffle 2) and a Llama decoder."""
    vision = {key: value for key, value in _vision_tower("", size, size // 4).items() if key != "model_type"}
    kwargs = dict(vision_config=vision, text_config=_text_config(tokenizer, "llama"), scale_factor=2,
                  image_token_id=tokenizer.convert_tokens_to_ids("<image>"), **token_roles(tokenizer))
    if family == "idefics3":
        from transformers import Idefics3Config
        return Idefics3Config(**kwargs)
    from transformers import SmolVLMConfig
    return SmolVLMConfig(**kwargs)


_BUILDERS = {
    "llava": (_llava_processor, _llava_config),
    "llava_onevision": (_onevision_processor, _onevision_config),
    "qwen2_vl": (lambda t, s: _qwen_processor(t, s, "qwen2_vl"), _qwen2_vl_config),
    "qwen2_5_vl": (lambda t, s: _qwen_processor(t, s, "qwen2_5_vl"), _qwen2_5_vl_config),
    "idefics3": (lambda t, s: _idefics_processor(t, s, "idefics3"), lambda t, s: _idefics_config(t, s, "idefics3")),
    "smolvlm": (lambda t, s: _idefics_processor(t, s, "smolvlm"), lambda t, s: _idefics_config(t, s, "smolvlm")),
}
