"""The local Hugging Face backend: any image-text-to-text model saved on disk (`model=vlm/hf model.path=DIR`).

The model and processor load with AutoModelForImageTextToText + AutoProcessor from a local directory, nothing
downloaded. A clip's frames go in as the family's processor expects them (several images, or one video where the
family takes videos), placed by the processor's own chat template: the user turn is the frames, then the question.
`answer` generates in batches with left padding (greedy by default) and decodes only the new tokens.
`answer_loss` is the per-sample mean NLL of the answer tokens, the answer being the assistant turn of the chat
template, computed from input embeddings so gradients reach them. `encode` and `loss_from_embeds` expose the pieces
PAT++ needs: the tokenised batch with the token positions of each question's text, and the loss from given
embeddings.
"""

from __future__ import annotations

import hashlib
import inspect
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from lanevil_train.vlm.backends.weight_files import check_weight_files
from lanevil_train.vlm.base import VLM, Frames, check_batch, is_clip_tensor

FRAMES_AS = ("auto", "images", "video")
DTYPES = ("auto", "float32", "bfloat16", "float16")
# Families whose models take a clip natively as one video; "auto" gives the frames to these as a video.
VIDEO_FAMILIES = ("qwen2_vl", "qwen2_5_vl", "qwen3_vl", "llava_onevision", "llava_next_video")
IGNORE_INDEX = -100
_QUESTION_MARK = "@@LANEVIL_QUESTION@@"
_ANSWER_MARK = "@@LANEVIL_ANSWER@@"
_WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pt", ".pth")
ADAPTER_CONFIG = "adapter_config.json"


@dataclass
class EncodedBatch:
    """A tokenised, left-padded batch: processor outputs on the model's device and where each text sits.

    inputs: what the model takes (input_ids, attention_mask, pixel values, grids...); question_spans[i] and
    answer_spans[i]: [start, end) token positions of sample i's question text and answer text in input_ids;
    labels: input_ids with IGNORE_INDEX everywhere but the answer tokens (None without answers).
    """

    inputs: dict
    question_spans: list[tuple[int, int]]
    answer_spans: list[tuple[int, int]] | None = None
    labels: object | None = None


class HFVLM(VLM):
    """A Hugging Face image-text-to-text model from a local directory, behind the VLM interface."""

    def __init__(self, path: str | Path, name: str | None = None, dtype: str = "auto", device: str = "auto",
                 max_new_tokens: int = 64, batch_size: int = 4, frames_as: str = "auto",
                 system_prompt: str | None = None, do_sample: bool = False, temperature: float = 1.0,
                 attn_implementation: str | None = None, seed: int = 0, adapter: str | Path | None = None,
                 merge_adapter: bool = False):
        """Load the model and processor saved at `path` (and the peft adapter at `adapter` on top of it, merged
        into the weights when `merge_adapter`); refuse bad settings naming the argument."""
        self.path = _check_model_dir(path)
        self.dtype_name = _choice("dtype", dtype, DTYPES)
        self.device = _resolve_device(device)
        self.model_type = _check_architecture(self.path)
        self.adapter = None if adapter is None else _check_adapter_dir(adapter)
        self.merge_adapter = bool(merge_adapter)
        self._settle(name, max_new_tokens, batch_size, frames_as, system_prompt, do_sample, temperature, seed)
        self.processor = _load_processor(self.path)
        self.model = _load_model(self.path, self.dtype_name, self.device, attn_implementation)
        if self.adapter is not None:
            self.model = _load_adapter(self.model, self.adapter, self.path, self.merge_adapter)
        self.frames_as = self._resolve_frames_as()

    @classmethod
    def wrap(cls, model, processor, path: str | Path, name: str | None = None, max_new_tokens: int = 64,
             batch_size: int = 4, frames_as: str = "auto", system_prompt: str | None = None, do_sample: bool = False,
             temperature: float = 1.0, seed: int = 0) -> "HFVLM":
        """An HFVLM around an already-loaded model (plain or peft-wrapped) and processor, e.g. one being trained,
        so training and evaluation share the same encode/loss code; `path` is the base model's directory."""
        self = cls.__new__(cls)
        self.path = _check_model_dir(path)
        self.model_type = _check_architecture(self.path)
        self.model, self.processor = model, processor
        self.dtype_name = str(model.dtype).removeprefix("torch.")
        self.device = str(next(model.parameters()).device)
        self.adapter, self.merge_adapter = None, False
        self._settle(name, max_new_tokens, batch_size, frames_as, system_prompt, do_sample, temperature, seed)
        self.frames_as = self._resolve_frames_as()
        return self

    def _settle(self, name, max_new_tokens, batch_size, frames_as, system_prompt, do_sample, temperature,
                seed) -> None:
        """Check and keep the generation and prompt settings, naming a bad argument."""
        self.name = name or self.path.name
        self.frames_as_setting = _choice("frames_as", frames_as, FRAMES_AS)
        self.max_new_tokens = _positive_int("max_new_tokens", max_new_tokens)
        self.batch_size = _positive_int("batch_size", batch_size)
        if not isinstance(temperature, (int, float)) or not temperature > 0:
            raise ValueError(f"temperature: expected a number > 0, got {temperature!r}")
        if system_prompt is not None and not isinstance(system_prompt, str):
            raise ValueError(f"system_prompt: expected a string or None, got {type(system_prompt).__name__}")
        self.system_prompt, self.do_sample, self.temperature = system_prompt, bool(do_sample), float(temperature)
        self.seed = int(seed)

    # ---- the VLM interface -------------------------------------------------------------------------------------

    def answer(self, clips: Sequence[Frames], questions: Sequence[str]) -> list[str]:
        """Greedy (or sampled) answers, batch_size pairs at a time, only the new tokens decoded and stripped."""
        return self.answer_encoded(clips, questions, self.encode)

    def answer_encoded(self, clips: Sequence[Frames], questions: Sequence[str], encode) -> list[str]:
        """`answer`, each batch_size pairs encoded by `encode(clips, questions) -> EncodedBatch` (e.g. `encode`
        with a defense prefix spliced in)."""
        import torch

        check_batch(clips, questions)
        answers: list[str] = []
        with torch.inference_mode():
            for start in range(0, len(questions), self.batch_size):
                stop = start + self.batch_size
                answers.extend(self.generate_encoded(encode(clips[start:stop], questions[start:stop])))
        return answers

    def answer_loss(self, clips: Sequence[Frames], questions: Sequence[str], answers: Sequence[str]):
        """Per-sample mean NLL [B] of each answer's tokens as the assistant turn, differentiable to the embeddings."""
        batch = self.encode(clips, questions, answers)
        return self.loss_from_embeds(batch, self.embed(batch))

    def identity(self) -> dict:
        """Path, a cheap hash of config + weight file names/sizes, and every setting that changes the answers."""
        return {"backend": type(self).__name__, "name": self.name, "path": str(self.path),
                "model_hash": model_dir_hash(self.path), "dtype": self.dtype_name,
                "max_new_tokens": self.max_new_tokens, "frames_as": self.frames_as, "system_prompt": self.system_prompt,
                "do_sample": self.do_sample, "temperature": self.temperature if self.do_sample else None,
                **({} if self.adapter is None else {"adapter": str(self.adapter), "adapter_hash":
                    adapter_dir_hash(self.adapter), "merge_adapter": self.merge_adapter})}

    # ---- pieces for losses over spliced embeddings (PAT++) -----------------------------------------------------

    def encode(self, clips: Sequence[Frames], questions: Sequence[str],
               answers: Sequence[str] | None = None, label_eos: bool = False) -> EncodedBatch:
        """The left-padded batch through the chat template (answers as the assistant turn when given), with the
        token spans of each question (and answer) and the answer-only labels. `clips`: per sample its uint8 frames,
        or one float tensor [B, frames, 3, H, W] in [0, 1] whose pixel values keep their gradient (the processors'
        own torch operations carry it: what training and the visual defenses use). With `label_eos` the labels also
        cover the end-of-turn token after each answer (inserted when the template puts none there), so a model
        trained on them learns to stop."""
        check_batch(clips, questions, answers)
        rendered = [self._render(clip, q, None if answers is None else answers[i], label_eos)
                    for i, (clip, q) in enumerate(zip(clips, questions))]
        texts = [text for text, _, _ in rendered]
        inputs = self._process(texts, clips)
        question_spans, answer_spans = self._locate_spans(texts, rendered, inputs)
        batch = EncodedBatch(inputs=inputs, question_spans=question_spans)
        if answers is not None:
            batch.answer_spans = answer_spans
            labelled = answer_spans
            if label_eos:
                ends = self._locate_spans(texts, [(t, q, self._end_chars(t, a)) for t, q, a in rendered], inputs)[1]
                labelled = [(start, end) for (start, _), (_, end) in zip(answer_spans, ends)]
            batch.labels = _answer_labels(inputs["input_ids"], labelled)
        return batch

    def embed(self, batch: EncodedBatch):
        """The input embeddings of the batch's token ids (a tensor in the graph of the embedding matrix)."""
        return self.model.get_input_embeddings()(batch.inputs["input_ids"])

    def loss_from_embeds(self, batch: EncodedBatch, inputs_embeds):
        """Per-sample mean NLL [B] of the labelled (answer) tokens, the model run on `inputs_embeds`."""
        import torch
        import torch.nn.functional as F

        if batch.labels is None:
            raise ValueError("batch: encoded without answers; pass answers to encode() to get labels")
        if tuple(inputs_embeds.shape[:2]) != tuple(batch.labels.shape):
            raise ValueError(f"inputs_embeds: expected shape [B, T, D] with [B, T] = {tuple(batch.labels.shape)}, "
                             f"got {tuple(inputs_embeds.shape)}")
        extra = {key: value for key, value in batch.inputs.items() if key != "input_ids"}
        logits = self.model(inputs_embeds=inputs_embeds, position_ids=self.position_ids(batch), use_cache=False,
                            **extra).logits
        labels = batch.labels[:, 1:]
        logits = logits if logits.dtype == torch.float64 else logits.float()  # float64 kept for exact checks
        nll = F.cross_entropy(logits[:, :-1].transpose(1, 2), labels, ignore_index=IGNORE_INDEX,
                              reduction="none")
        counts = (labels != IGNORE_INDEX).sum(dim=1)
        return nll.sum(dim=1) / torch.clamp(counts, min=1)

    def position_ids(self, batch: EncodedBatch):
        """Position ids that skip the left padding (3-D M-RoPE ids for the Qwen-VL families), as generate uses."""
        inputs = batch.inputs
        model = self.model.get_base_model() if hasattr(self.model, "get_base_model") else self.model
        base = getattr(model, "model", None)
        if hasattr(base, "get_rope_index") and "mm_token_type_ids" in inputs:
            accepted = inspect.signature(base.get_rope_index).parameters
            kwargs = {key: value for key, value in inputs.items() if key in accepted}
            return base.get_rope_index(**kwargs)[0]
        mask = inputs["attention_mask"].long()
        return (mask.cumsum(-1) - 1).masked_fill(mask == 0, 0)

    # ---- internals ---------------------------------------------------------------------------------------------

    def _resolve_frames_as(self) -> str:
        """'images' or 'video': what "auto" means for this family, and a check that the processor can take it."""
        takes_video = getattr(self.processor, "video_processor", None) is not None and \
            getattr(self.processor, "video_token", None) is not None
        if self.frames_as_setting == "video" and not takes_video:
            raise ValueError(f"frames_as: 'video' but the processor at {self.path} ({type(self.processor).__name__}) "
                             f"takes no videos; use 'images' or 'auto'")
        if self.frames_as_setting == "auto":
            return "video" if takes_video and self.model_type in VIDEO_FAMILIES else "images"
        return self.frames_as_setting

    def end_tokens(self) -> list[str]:
        """The strings of the tokens that end the model's turn: the generation config's eos ids and the
        tokenizer's eos token."""
        tokenizer = self.processor.tokenizer
        ids = getattr(getattr(self.model, "generation_config", None), "eos_token_id", None)
        ids = [] if ids is None else [ids] if isinstance(ids, int) else list(ids)
        tokens = tokenizer.convert_ids_to_tokens(ids) + [tokenizer.eos_token]
        return list(dict.fromkeys(token for token in tokens if token))

    def _end_chars(self, text: str, answer_chars: tuple[int, int]) -> tuple[int, int]:
        """Character span of the end-of-turn token that follows the answer in `text` (whitespace between allowed)."""
        rest = text[answer_chars[1]:]
        gap = len(rest) - len(rest.lstrip())
        for token in self.end_tokens():
            if rest[gap:].startswith(token):
                start = answer_chars[1] + gap
                return start, start + len(token)
        raise ValueError(f"chat template of {self.path}: no end-of-turn token ({', '.join(self.end_tokens())}) "
                         f"after the answer; expected one to label")

    def _render(self, clip: Frames, question: str, answer: str | None,
                label_eos: bool = False) -> tuple[str, tuple[int, int], tuple[int, int] | None]:
        """The chat-template text of one sample and the character spans of its question and answer in it."""
        media = [{"type": "video"}] if self.frames_as == "video" else [{"type": "image"}] * len(clip)
        messages = []
        if self.system_prompt is not None:
            messages.append({"role": "system", "content": [{"type": "text", "text": self.system_prompt}]})
        messages.append({"role": "user", "content": media + [{"type": "text", "text": _QUESTION_MARK}]})
        if answer is not None:
            messages.append({"role": "assistant", "content": [{"type": "text", "text": _ANSWER_MARK}]})
        template = self.processor.apply_chat_template(messages, add_generation_prompt=answer is None, tokenize=False)
        if isinstance(template, list):
            template = template[0]
        text, q_span, a_span = _fill_marks(template, question.strip(), None if answer is None else answer.strip(),
                                           self.path)
        if label_eos and a_span is not None and not self._ends_after(text, a_span):
            eos = self.processor.tokenizer.eos_token
            if not eos:
                raise ValueError(f"tokenizer of {self.path}: no eos token to end the answer with; cannot train it to "
                                 f"stop (set train_eos=false)")
            text = text[:a_span[1]] + eos + text[a_span[1]:]
        return text, q_span, a_span

    def _ends_after(self, text: str, answer_chars: tuple[int, int]) -> bool:
        """Whether an end-of-turn token follows the answer in `text` (after whitespace at most)."""
        rest = text[answer_chars[1]:].lstrip()
        return any(rest.startswith(token) for token in self.end_tokens())

    def _process(self, texts: list[str], clips: Sequence[Frames]) -> dict:
        """Processor outputs (left-padded) as tensors on the model's device, floats in the model's dtype."""
        import torch

        self.processor.tokenizer.padding_side = "left"
        if is_clip_tensor(clips):  # float [B, frames, 3, H, W] in [0, 1]: the processors' torch ops keep the graph
            clips = [clip * 255.0 for clip in clips]
        if self.frames_as == "video":
            media = {"videos": [clip if is_clip_tensor(clip) else np.stack(list(clip)) for clip in clips]}
        else:
            media = {"images": [list(clip) for clip in clips]}
        outputs = self.processor(text=texts, padding=True, return_tensors="pt", **media)
        dtype = self.model.dtype
        return {key: (value.to(self.device, dtype) if torch.is_floating_point(value) else value.to(self.device))
                for key, value in outputs.items() if isinstance(value, torch.Tensor)}

    def _locate_spans(self, texts, rendered, inputs):
        """Token spans of questions and answers in the left-padded ids, from the text's own tokenisation.

        The processor expands each frame placeholder into many tokens and changes nothing else, so a text that
        comes after every placeholder keeps its tokens' distance from the end of the padded row, and one before
        every placeholder (a template that puts the question before the frames) its distance from the first
        unpadded token: placed that way and checked token by token."""
        encoded = self.processor.tokenizer(texts, return_offsets_mapping=True)
        input_ids, length = inputs["input_ids"], inputs["input_ids"].shape[1]
        placeholders = {getattr(self.processor, name, None) for name in ("image_token", "video_token")} - {None}
        placeholder_ids = {self.processor.tokenizer.convert_tokens_to_ids(token) for token in placeholders}
        questions, answers = [], []
        for i, (_, q_chars, a_chars) in enumerate(rendered):
            ids, offsets = encoded["input_ids"][i], encoded["offset_mapping"][i]
            marks = [k for k, token in enumerate(ids) if token in placeholder_ids] or [-1]
            after, before = length - len(ids), length - int(inputs["attention_mask"][i].sum())
            spans = [("question", q_chars, questions)] + ([("answer", a_chars, answers)] if a_chars is not None else [])
            for what, chars, found in spans:
                first, last = _overlapping_tokens(offsets, chars, f"{what} {i}")
                shift = after if first > marks[-1] else before if last < marks[0] else None
                if shift is None or input_ids[i, first + shift:last + 1 + shift].tolist() != ids[first:last + 1]:
                    raise RuntimeError(f"sample {i}: the processor's token ids of the {what} differ from the text's "
                                       f"own tokenisation in {self.path}; cannot place the question and answer tokens")
                found.append((first + shift, last + 1 + shift))
        return questions, answers

    def generate_encoded(self, batch: EncodedBatch) -> list[str]:
        """Answers to an encoded batch (a prompt without answers, possibly with a defense prefix spliced in)."""
        import torch

        options = dict(max_new_tokens=self.max_new_tokens, do_sample=self.do_sample)
        if self.do_sample:
            torch.manual_seed(self.seed)
            options["temperature"] = self.temperature
        pad = self.processor.tokenizer.pad_token_id
        if pad is not None:
            options["pad_token_id"] = pad
        output = self.model.generate(**batch.inputs, **options)
        new_tokens = output[:, batch.inputs["input_ids"].shape[1]:]
        return [text.strip() for text in self.processor.tokenizer.batch_decode(new_tokens, skip_special_tokens=True)]


def model_dir_hash(path: str | Path) -> str:
    """A cheap fingerprint of a saved model: config.json's bytes and the names and sizes of its weight files."""
    path = Path(path)
    digest = hashlib.sha256((path / "config.json").read_bytes())
    for file in sorted(path.iterdir()):
        if file.is_file() and file.name.endswith(_WEIGHT_SUFFIXES):
            digest.update(f"{file.name}:{file.stat().st_size}".encode())
    return digest.hexdigest()[:16]


def adapter_dir_hash(path: str | Path) -> str:
    """A cheap fingerprint of a saved peft adapter: adapter_config.json's bytes and its weight files' sizes."""
    path = Path(path)
    digest = hashlib.sha256((path / ADAPTER_CONFIG).read_bytes())
    for file in sorted(path.iterdir()):
        if file.is_file() and file.name.endswith(_WEIGHT_SUFFIXES):
            digest.update(f"{file.name}:{file.stat().st_size}".encode())
    return digest.hexdigest()[:16]


def _fill_marks(template: str, question: str, answer: str | None, path: Path):
    """Put question and answer where the chat template placed their marks; their character spans."""
    for mark, wanted in ((_QUESTION_MARK, True), (_ANSWER_MARK, answer is not None)):
        if wanted and template.count(mark) != 1:
            raise ValueError(f"chat template of {path}: the rendered conversation holds the "
                             f"{'question' if mark == _QUESTION_MARK else 'answer'} {template.count(mark)} times, "
                             f"expected once")
    q_start = template.index(_QUESTION_MARK)
    text = template[:q_start] + question + template[q_start + len(_QUESTION_MARK):]
    q_span = (q_start, q_start + len(question))
    if answer is None:
        return text, q_span, None
    a_start = text.index(_ANSWER_MARK)
    if a_start < q_span[1]:
        raise ValueError(f"chat template of {path}: the answer comes before the question; expected the user turn "
                         f"first")
    text = text[:a_start] + answer + text[a_start + len(_ANSWER_MARK):]
    return text, q_span, (a_start, a_start + len(answer))


def _overlapping_tokens(offsets, chars: tuple[int, int], what: str) -> tuple[int, int]:
    """First and last index of the tokens whose character offsets overlap `chars`."""
    start, end = chars
    hits = [j for j, (a, b) in enumerate(offsets) if b > start and a < end and b > a]
    if not hits:
        raise ValueError(f"{what}: empty after stripping, or no token covers it; expected non-empty text")
    return hits[0], hits[-1]


def _answer_labels(input_ids, answer_spans):
    """input_ids with IGNORE_INDEX everywhere but each sample's answer span."""
    labels = input_ids.new_full(input_ids.shape, IGNORE_INDEX)
    for i, (start, end) in enumerate(answer_spans):
        labels[i, start:end] = input_ids[i, start:end]
    return labels


def _check_model_dir(path) -> Path:
    """`path` as a directory holding config.json and whole weight files, else an error naming it."""
    if not isinstance(path, (str, Path)) or not str(path):
        raise ValueError(f"model.path: expected a directory of a saved Hugging Face model, got {path!r}")
    path = Path(path).expanduser().resolve()
    if not path.is_dir():
        raise FileNotFoundError(f"model.path {path}: not a directory; expected a model saved with save_pretrained")
    if not (path / "config.json").is_file():
        raise FileNotFoundError(f"model.path {path}: no config.json, so not a saved Hugging Face model; expected a "
                                f"directory written by save_pretrained")
    check_weight_files(path, "model.path")
    return path


def _check_architecture(path: Path) -> str:
    """The model_type in path/config.json when AutoModelForImageTextToText knows it, else a ValueError."""
    from transformers.models.auto.modeling_auto import MODEL_FOR_IMAGE_TEXT_TO_TEXT_MAPPING_NAMES

    try:
        config = json.loads((path / "config.json").read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"{path / 'config.json'}: unreadable ({error})") from error
    model_type = config.get("model_type") if isinstance(config, dict) else None
    if model_type not in MODEL_FOR_IMAGE_TEXT_TO_TEXT_MAPPING_NAMES:
        raise ValueError(f"{path / 'config.json'}: model_type {model_type!r} is not an image-text-to-text "
                         f"architecture (AutoModelForImageTextToText); expected a vision-language model such as "
                         f"llava, llava_onevision, qwen2_vl, qwen2_5_vl, idefics3 or smolvlm")
    return model_type


def _load_processor(path: Path):
    """AutoProcessor from `path` (local files only) with an image processor and a chat template, else an error."""
    from transformers import AutoProcessor

    try:
        processor = AutoProcessor.from_pretrained(path, local_files_only=True)
    except ImportError as error:
        raise ImportError(f"processor at {path}: needs a package that is not installed ({error})") from error
    except (OSError, ValueError, TypeError, KeyError) as error:
        raise FileNotFoundError(f"processor at {path}: cannot be loaded ({error}); expected processor, "
                                f"image processor and tokenizer files saved with the model") from error
    if getattr(processor, "image_processor", None) is None or getattr(processor, "tokenizer", None) is None:
        raise FileNotFoundError(f"processor at {path}: missing (AutoProcessor gave {type(processor).__name__}); "
                                f"expected an image processor and a tokenizer saved with the model")
    if not getattr(processor, "chat_template", None):
        raise ValueError(f"processor at {path}: no chat template; expected chat_template.jinja or the processor's "
                         f"chat_template saved with the model")
    return processor


def _load_model(path: Path, dtype: str, device: str, attn_implementation: str | None):
    """AutoModelForImageTextToText from `path` (local files only) in `dtype` on `device`, in eval mode."""
    import torch
    from transformers import AutoModelForImageTextToText

    options = {"local_files_only": True, "dtype": dtype if dtype == "auto" else getattr(torch, dtype)}
    if attn_implementation is not None:
        options["attn_implementation"] = attn_implementation
    try:
        model = AutoModelForImageTextToText.from_pretrained(path, **options)
    except (OSError, ValueError) as error:
        raise ValueError(f"model at {path}: cannot be loaded as image-text-to-text ({error})") from error
    return model.to(device).eval()


def _check_adapter_dir(path) -> Path:
    """`path` as a directory holding a peft adapter (adapter_config.json) and whole weight files, else an error
    naming it."""
    if not isinstance(path, (str, Path)) or not str(path):
        raise ValueError(f"model.adapter: expected a directory of a saved peft adapter, got {path!r}")
    path = Path(path).expanduser().resolve()
    if not path.is_dir():
        raise FileNotFoundError(f"model.adapter {path}: not a directory; expected a peft adapter saved with "
                                f"save_pretrained")
    if not (path / ADAPTER_CONFIG).is_file():
        raise ValueError(f"model.adapter {path}: no {ADAPTER_CONFIG}, so not a peft adapter; expected a directory "
                         f"written by a LoRA run's save_model (a merged or fully fine-tuned model loads as "
                         f"model.path instead)")
    check_weight_files(path, "model.adapter")
    return path


def _load_adapter(model, adapter: Path, base: Path, merge: bool):
    """`model` with the peft adapter at `adapter` on top (merged into the weights when `merge`), in eval mode;
    an adapter that does not fit the model is an error naming both paths."""
    import warnings

    from peft import PeftModel

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            model = PeftModel.from_pretrained(model, adapter, is_trainable=False)
        except (RuntimeError, ValueError, KeyError, TypeError) as error:
            raise ValueError(f"model.adapter {adapter}: does not fit the model at {base} ({error}); expected an "
                             f"adapter trained on that model") from error
    missing = [str(w.message) for w in caught if "missing adapter keys" in str(w.message).lower()]
    if missing:
        raise ValueError(f"model.adapter {adapter}: does not fit the model at {base}: {missing[0][:300]}")
    return (model.merge_and_unload() if merge else model).eval()


def _resolve_device(device: str) -> str:
    """'auto' -> cuda when available else cpu; any other value must be a torch device string."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        return str(torch.device(device))
    except (RuntimeError, TypeError) as error:
        raise ValueError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {device!r}") from error


def _choice(name: str, value, allowed: tuple[str, ...]) -> str:
    """`value` when it is one of `allowed`, else a ValueError naming the argument."""
    if value not in allowed:
        raise ValueError(f"{name}: expected one of {', '.join(allowed)}, got {value!r}")
    return value


def _positive_int(name: str, value) -> int:
    """`value` as an int >= 1, else a ValueError naming the argument."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
    return value
