"""The embedded VLM: a small Qwen2-VL built here from a config, that learns the clip QA on a CPU in minutes.

It is the project's offline default VLM (`model=vlm/embedded`): nothing is downloaded, and it is saved with
`save_pretrained`, so it loads through AutoModelForImageTextToText + AutoProcessor and runs through the very same
`vlm/backends/hf.py` code (HFVLM: generation, answer loss, LoRA, prefix splicing) as any downloaded model. It is a small
baseline trained on the simulated clips, never one of the paper's models.

Choices (defaults; every size is a keyword of `build_embedded_vlm`):
  * family: Qwen2-VL (`qwen2_vl`), because it takes a clip natively as one video of any aspect ratio: the 6
    frames are cut into 2-frame x 8x8-pixel patches (temporal patch 2, patch 8) and 2x2 patches are merged
    into one token, so a 64x112 clip is 3 x 4 x 7 = 84 vision tokens (LLaVA would crop the frames square and
    spend a token per patch per frame).
  * image resolution: the processor feeds the frames at `frame_size` (default (64, 112), H x W, multiples of
    16): its pixel bounds are that frame's area, so frames rendered at that size pass unresized and larger
    frames are scaled down to about that area.
  * vision tower: 2 blocks, width 96, 4 heads, projected (merger) into the decoder's width.
  * decoder: Qwen2 with M-RoPE, width 128, 4 layers, 4 heads (2 key/value heads), MLP 384; its M-RoPE base and
    sections (ROPE_THETA) let it tell the 7 columns and 4 rows of a frame's tokens apart.
  * vocabulary: a byte-level BPE tokenizer of 1024 ids trained here on the QA corpus given (the training
    split's questions, options and answers) plus vlm/tokenizer.py's base corpus, with Qwen2-VL's special tokens; any
    text still encodes (byte fallback), so no question is ever unknown.
  * parameters: 1,434,496 with the defaults (vision 0.38 M, decoder 0.92 M, head 0.13 M; PARAMETER_RANGE
    bounds it; `count_parameters` tells).
The chat template (CHAT_TEMPLATE) has Qwen2-VL's turns with the user's question before the video, so that every
answer token sits at the same M-RoPE offset from each vision token.
Training (the recipe in conf/model/vlm/embedded.yaml; `fit_answers` is the same loop without Lightning, which
benchmarks/bench_embedded.py uses): first `pretrain_vision` teaches the vision tower the train clips' scene truth
(lane count, ego lane, road shape and bend, weather, ...) through a linear probe that is then dropped; then AdamW
on the answer loss (and end-of-turn token), the tower frozen, of (clip variant, QA) pairs of the train split, clean
and perturbed, plus the clip's training aids (qa.training_aids: a scene description and open questions on its lane
count, ego lane, steering and safe action). On the QA alone it learns only the questions' text prior. 1,500 steps
of 16 (7 min here), 300 held-out cases: yes/no accuracy 85.5 % and choice 36.8 % against a majority answer of
51.0 % / 25.5 %; open answers name the weather 97.9 % of the time, the ego lane 85.4 % and the lane count 52.3 %
(the most common value: 14.2 %, 32.3 %, 37.6 %), but the steering the road's bend asks for only 54.0 %, below
always answering "straight" (59.8 %): it has not learned the bend (docs/vlm.md, "The embedded VLM").
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

from lanevil_train.progress import progress_counter
from lanevil_train.vlm.clips.qa import SCENE_CLASSES, UNKNOWN_CLASS, mirror_scene_classes
from lanevil_train.vlm.clips.qa_records import prompt_text
from lanevil_train.vlm.tokenizer import qwen_ids, token_roles, train_tokenizer

FAMILY = "qwen2_vl"
DEFAULT_FRAME_SIZE = (64, 112)
PATCH, MERGE, TEMPORAL = 8, 2, 2
PARAMETER_RANGE = (0.8e6, 2.5e6)  # what the default sizes give (1.43 M), with room for the vocabulary
DEFAULT_SIZES = {"hidden": 128, "layers": 4, "heads": 4, "kv_heads": 2, "intermediate": 384,
                 "vision_dim": 96, "vision_depth": 2, "vision_heads": 4, "vocab_size": 1024}

# Where the decoder can see a vision token. Qwen2-VL's tower has no absolute positions, so only the decoder's M-RoPE
# tells the 4 x 7 tokens of a frame apart, and Qwen's own settings (base 10000, the slowest frequencies for the
# width) turn the width by at most 0.003 rad a column: blind to left and right. A base of 10 with sections of
# 1/8, 1/4 and 5/8 of the rotary pairs for time, height and width turns a column by 0.12-0.42 rad and a row by
# 0.49-0.75 rad (time, 3 steps a clip, needs least).
ROPE_THETA = 10.0

# The chat template: Qwen2-VL's turns, but the user's text before the video. With M-RoPE a text token's position
# follows the tokens before it, so after a question of variable length the answer would meet the vision tokens at
# a different relative position in every sample; with the question first, the video starts where the question
# ends and an answer token sits at the same offset from each vision token whatever the question, so attending to
# a column is learnable (held-out ego lane named 83.6 % instead of 75.2 %, benchmarks/RESULTS.md).
CHAT_TEMPLATE = (
    "{% for message in messages %}{% if loop.first and message['role'] != 'system' %}"
    "{{ '<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n' }}{% endif %}"
    "{{ '<|im_start|>' + message['role'] + '\n' }}"
    "{% for c in message['content'] %}{% if c['type'] == 'text' %}{{ c['text'] }}{% endif %}{% endfor %}"
    "{% for c in message['content'] %}{% if c['type'] == 'image' %}{{ '<|vision_start|><|image_pad|><|vision_end|>' }}"
    "{% elif c['type'] == 'video' %}{{ '<|vision_start|><|video_pad|><|vision_end|>' }}{% endif %}{% endfor %}"
    "{{ '<|im_end|>\n' }}{% endfor %}{% if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}{% endif %}")


def check_sizes(size: dict) -> dict:
    """DEFAULT_SIZES overridden by `size`, each a positive int and the widths divisible by their heads."""
    unknown = sorted(set(size) - set(DEFAULT_SIZES))
    if unknown:
        raise ValueError(f"size: unknown keys {unknown}; expected some of {', '.join(DEFAULT_SIZES)}")
    sizes = {**DEFAULT_SIZES, **size}
    for key, value in sizes.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"size.{key}: expected an integer >= 1, got {value!r}")
    head_dim, rest = divmod(sizes["hidden"], sizes["heads"])
    if rest or head_dim % 16:
        raise ValueError(f"size.hidden ({sizes['hidden']}) / size.heads ({sizes['heads']}): expected a head width "
                         f"that is a multiple of 16 (M-RoPE splits its rotary pairs in 3 sections of 1/8, 1/4, 5/8)")
    if sizes["heads"] % sizes["kv_heads"]:
        raise ValueError(f"size.kv_heads ({sizes['kv_heads']}): expected a divisor of size.heads ({sizes['heads']})")
    if sizes["vision_dim"] % sizes["vision_heads"]:
        raise ValueError(f"size.vision_dim ({sizes['vision_dim']}): expected a multiple of size.vision_heads "
                         f"({sizes['vision_heads']})")
    if sizes["vocab_size"] < 300:
        raise ValueError(f"size.vocab_size: expected at least 300 (256 bytes + special tokens), "
                         f"got {sizes['vocab_size']}")
    return sizes


def check_frame_size(frame_size) -> tuple[int, int]:
    """(H, W) as two ints, each a multiple of 16 (patch 8 x merge 2) and at least 16, else a ValueError."""
    step = PATCH * MERGE
    if (not isinstance(frame_size, (list, tuple)) or len(frame_size) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= step and v % step == 0
                       for v in frame_size)):
        raise ValueError(f"frame_size: expected (H, W), two multiples of {step} that are at least {step}, "
                         f"got {frame_size!r}")
    return int(frame_size[0]), int(frame_size[1])


def train_qa_tokenizer(corpus: Sequence[str], vocab_size: int):
    """A byte-level BPE tokenizer of `vocab_size` ids trained on `corpus` with Qwen2-VL's special tokens."""
    return train_tokenizer(FAMILY, corpus, vocab_size)


def make_processor(tokenizer, frame_size: tuple[int, int]):
    """Qwen2-VL image and video processors (patch 8, merge 2) that keep about `frame_size`'s area per frame."""
    from transformers import Qwen2VLImageProcessor, Qwen2VLProcessor, Qwen2VLVideoProcessor

    area = frame_size[0] * frame_size[1]
    pixels = {"size": {"shortest_edge": area, "longest_edge": area}, "patch_size": PATCH,
              "temporal_patch_size": TEMPORAL, "merge_size": MERGE}
    images = Qwen2VLImageProcessor(**pixels)
    videos = Qwen2VLVideoProcessor(**pixels, do_sample_frames=False, cap_pixels_per_frame=True)
    return Qwen2VLProcessor(images, tokenizer, videos, chat_template=CHAT_TEMPLATE)


def make_config(tokenizer, sizes: dict):
    """The Qwen2-VL config of `sizes` with the token ids of `tokenizer`."""
    from transformers import Qwen2VLConfig

    half = sizes["hidden"] // sizes["heads"] // 2  # rotary frequency pairs per head
    section = [half // 8, half // 4, half - half // 8 - half // 4]  # time, height, width (ROPE_THETA)
    vision = dict(depth=sizes["vision_depth"], embed_dim=sizes["vision_dim"], hidden_size=sizes["hidden"],
                  num_heads=sizes["vision_heads"], mlp_ratio=2, patch_size=PATCH, spatial_merge_size=MERGE,
                  temporal_patch_size=TEMPORAL)
    text = dict(model_type="qwen2_vl_text", vocab_size=len(tokenizer), hidden_size=sizes["hidden"],
                intermediate_size=sizes["intermediate"], num_hidden_layers=sizes["layers"],
                num_attention_heads=sizes["heads"], num_key_value_heads=sizes["kv_heads"],
                max_position_embeddings=2048, rope_parameters={"rope_type": "default", "rope_theta": ROPE_THETA,
                                                               "mrope_section": section},
                **token_roles(tokenizer), bos_token_id=None)
    return Qwen2VLConfig(vision_config=vision, text_config=text, **qwen_ids(tokenizer), **token_roles(tokenizer),
                         bos_token_id=None)


def make_embedded_vlm(corpus: Sequence[str], frame_size=DEFAULT_FRAME_SIZE, seed: int = 0, **size):
    """(model, processor) of a random-weight embedded VLM in memory; the same arguments give the same weights."""
    import torch
    from transformers import AutoModelForImageTextToText, GenerationConfig

    if isinstance(corpus, str) or not all(isinstance(text, str) for text in corpus):
        raise ValueError("corpus: expected a sequence of strings (the QA texts to train the tokenizer on)")
    frame_size = check_frame_size(tuple(frame_size) if isinstance(frame_size, list) else frame_size)
    sizes = check_sizes(size)
    tokenizer = train_qa_tokenizer(corpus, sizes["vocab_size"])
    processor = make_processor(tokenizer, frame_size)
    config = make_config(tokenizer, sizes)
    torch.manual_seed(seed)
    model = AutoModelForImageTextToText.from_config(config).eval()
    model.generation_config = GenerationConfig(**token_roles(tokenizer))
    return model, processor


def build_embedded_vlm(out_dir: str | os.PathLike, corpus: Sequence[str], frame_size=DEFAULT_FRAME_SIZE,
                       seed: int = 0, **size) -> Path:
    """Build the random-weight embedded VLM (tokenizer trained on `corpus`) and save it whole at `out_dir`."""
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"out_dir {out}: exists and is not empty; expected a new or empty directory")
    model, processor = make_embedded_vlm(corpus, frame_size, seed, **size)
    save_model_dir(model, processor, out)
    return out


def save_model_dir(model, processor, out: Path) -> None:
    """Save model + processor into a staging folder, then rename it to `out`: a kill never leaves half a model."""
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        model.save_pretrained(staging)
        processor.save_pretrained(staging)
        if out.exists():
            shutil.rmtree(out) if any(out.iterdir()) else out.rmdir()
        os.replace(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def count_parameters(model) -> int:
    """How many weights the model has (vision tower, merger, decoder and head; tied weights counted once)."""
    return sum(p.numel() for p in model.parameters())


def qa_corpus(qas: Sequence[dict]) -> list[str]:
    """The texts of QA records (question, options, answer) a tokenizer should be trained on."""
    texts = []
    for i, qa in enumerate(qas):
        if not isinstance(qa, dict) or not isinstance(qa.get("question"), str) or not isinstance(qa.get("answer"),
                                                                                                  str):
            raise ValueError(f"qas[{i}]: expected a QA record with string 'question' and 'answer'")
        texts.append(prompt_text(qa) if qa.get("type") == "choice" else qa["question"])
        texts.append(qa["answer"])
    return texts


def vision_tokens(model, processor, clips):
    """The vision tower's output for each clip (a video) [B, tokens, hidden]: what the decoder reads; every clip of
    the batch must have the same frame size."""
    import torch

    inputs = processor.video_processor(videos=[np.stack([np.asarray(f) for f in clip]) for clip in clips],
                                       return_tensors="pt")
    pixels = inputs["pixel_values_videos"].to(model.device, model.dtype)
    tokens = model.model.get_video_features(pixels, inputs["video_grid_thw"].to(model.device)).pooler_output
    if len({t.shape for t in tokens}) != 1:
        raise ValueError("clips: expected frames of one size (their token counts differ)")
    return torch.stack(list(tokens))


def pretrain_vision(model, processor, sample_batch, steps: int, lr: float = 1e-3, log=None,
                    progress: str = "auto", mirror: bool = True, seed: int = 0) -> list[float]:
    """Pretrain the vision tower (patch embedding, blocks, merger) in place to tell a clip's scene truth: a linear
    probe on its flattened output tokens learns every SCENE_CLASSES fact (lane count, ego lane, road shape and bend,
    weather, setting, wet surface, the ego lane's markings) by cross-entropy, and is then discarded.
    `sample_batch(step) -> (clips, classes [B, len(SCENE_CLASSES)])` (qa.scene_classes); with `mirror`, about half
    of each batch is flipped left-right with its classes mirrored (`mirrored_batch`, drawn from `seed`); `progress`
    a progress.MODES display. The loss of each step, in order.

    Why: trained from scratch on the answer loss alone, the decoder reads only what an average over the vision
    tokens shows (weather, light), never where the lines are; a tower that has learned the scene's geometry first,
    then kept frozen (fine_tune.freeze_vision), gives it features to read. The mirror images make left and right
    bends equally common (right ones are twice as common in the simulator) and keep the tower from telling them
    apart by the scenery; without them the decoder answered "right" for most straight roads (benchmarks/RESULTS.md)."""
    import math

    import torch

    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an integer >= 1, got {steps!r}")
    if not isinstance(lr, (int, float)) or not lr > 0:
        raise ValueError(f"lr: expected a number > 0, got {lr!r}")
    sizes = [len(values) for values in SCENE_CLASSES.values()]
    rng = np.random.default_rng(seed)
    tower = model.model.visual.train()
    probe = None
    losses: list[float] = []
    bar = progress_counter(steps, desc="vision pretraining", unit="step", mode=progress)
    for step in range(steps):
        clips, classes = sample_batch(step)
        if np.shape(classes) != (len(clips), len(sizes)):
            raise ValueError(f"sample_batch: expected classes of shape ({len(clips)}, {len(sizes)}), "
                             f"got {np.shape(classes)}")
        if mirror:
            clips, classes = mirrored_batch(clips, classes, rng.random(len(clips)) < 0.5)
        classes = torch.as_tensor(np.asarray(classes), dtype=torch.long, device=model.device)
        features = vision_tokens(model, processor, clips).flatten(1)
        if probe is None:
            probe = torch.nn.Linear(features.shape[1], sum(sizes)).to(model.device, features.dtype)
            params = [*tower.parameters(), *probe.parameters()]
            optimizer = torch.optim.AdamW(params, lr=lr, weight_decay=0.01)
            schedule = torch.optim.lr_scheduler.LambdaLR(
                optimizer, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, steps) / steps)))
        logits = probe(features).split(sizes, dim=1)
        loss = sum(torch.nn.functional.cross_entropy(part, classes[:, k], ignore_index=UNKNOWN_CLASS)
                   for k, part in enumerate(logits) if (classes[:, k] != UNKNOWN_CLASS).any())
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        schedule.step()
        losses.append(float(loss.detach()))
        bar.update(1)
        if log is not None and (step + 1) % 50 == 0:
            log(f"vision pretraining step {step + 1}/{steps}: loss {sum(losses[-50:]) / 50:.3f}")
    bar.close()
    tower.eval()
    return losses


def mirrored_batch(clips, classes, flip) -> tuple[list, list]:
    """The batch with clip i flipped left-right (every frame) and its classes mirrored (qa.mirror_scene_classes)
    where flip[i]; the other clips and classes unchanged."""
    out_clips, out_classes = [], []
    for clip, cls, flipped in zip(clips, classes, flip):
        out_clips.append([np.ascontiguousarray(np.asarray(frame)[:, ::-1]) for frame in clip] if flipped else clip)
        out_classes.append(mirror_scene_classes(cls) if flipped else list(cls))
    return out_clips, out_classes


GREY = 128  # the blind ablation's frames: the same uniform grey as BlindVLM


def fit_answers(vlm, sample_batch, steps: int, lr: float = 2e-3, warmup: int = 30, weight_decay: float = 0.01,
                log=None, log_every: int = 25, label_eos: bool = True) -> list[float]:
    """Train an HFVLM's weights in place for `steps` AdamW steps (linear warmup, cosine decay) on the answer loss
    of `sample_batch(step) -> (clips, questions, answers)`; the mean loss of each step, in order. With `label_eos`
    (as task=train's fine_tune.train_eos) the end-of-turn token after each answer is learned too, so the model
    stops after its answer instead of running on into other answers' phrases."""
    import math

    import torch

    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an integer >= 1, got {steps!r}")
    if not isinstance(lr, (int, float)) or not lr > 0:
        raise ValueError(f"lr: expected a number > 0, got {lr!r}")
    model = vlm.model.train()
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=lr,
                                  weight_decay=weight_decay)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: min(1.0, (s + 1) / max(1, warmup))
                                                 * 0.5 * (1 + math.cos(math.pi * min(s, steps) / steps)))
    losses = []
    for step in range(steps):
        clips, questions, answers = sample_batch(step)
        batch = vlm.encode(clips, questions, answers, label_eos=label_eos)
        loss = vlm.loss_from_embeds(batch, vlm.embed(batch)).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        schedule.step()
        losses.append(float(loss.detach()))
        if log is not None and (step + 1) % log_every == 0:
            log(f"step {step + 1}/{steps}: loss {sum(losses[-log_every:]) / log_every:.3f}")
    model.eval()
    return losses
