"""PAT++ (the paper's §4.2): a defense prefix of n discrete tokens before the question, tuned by greedy coordinate
gradient (GCG, vlm/defenses/gcg.py) while the model's weights stay frozen.

The prefix minimises  alpha * L_bgn + (1 - alpha) * L_hard:
  * L_bgn, on benign examples: the NLL of the reference answer with the prefix;
  * L_hard, on hard examples: the NLL of RES_GOAL ("I will focus on the factors affecting the road"), as the paper
    writes it, or RES_GOAL followed by the reference answer (`hard_target="goal_then_answer"`).
Each term is the mean over its examples of a sample's mean NLL per target token (`HFVLM.loss_from_embeds`).

The prefix is spliced into the token ids right before each question's first token (gcg.splice_prefix): after the
image tokens in every family whose chat template puts the frames first, and before the question (and so before the
video) in the embedded VLM's question-first template.
"""

from __future__ import annotations

import io
import json
import math
import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from lanevil_train.files.atomic import atomic_write_bytes
from lanevil_train.vlm.backends.hf import HFVLM, EncodedBatch
from lanevil_train.vlm.base import VLM, Frames
from lanevil_train.vlm.defenses.gcg import (
    ControlObjective,
    Examples,
    Part,
    allowed_tokens,
    embed_scale,
    gcg_step,
    initial_prefix,
    splice_prefix,
)

RES_GOAL = "I will focus on the factors affecting the road"
HARD_TARGETS = ("goal", "goal_then_answer")
PREFIX_FILE = "prefix.json"


def hard_target(answer: str, mode: str = "goal") -> str:
    """A hard example's target: RES_GOAL alone (the paper), or RES_GOAL then the reference answer."""
    if mode == "goal":
        return RES_GOAL
    if mode == "goal_then_answer":
        return f"{RES_GOAL}. {answer.strip()}"
    raise ValueError(f"defense.hard_target: expected one of {', '.join(HARD_TARGETS)}, got {mode!r}")


def hard_mask(scores: Sequence[float]) -> list[bool]:
    """Which examples are hard, as AAM++ chooses them: those whose score is below the mean of all scores."""
    if not scores:
        raise ValueError("scores: expected at least one example's score, got none")
    values = [float(s) for s in scores]
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"scores: expected finite numbers, got {[v for v in values if not math.isfinite(v)][:3]}")
    mean = sum(values) / len(values)
    return [v < mean for v in values]


# ---- the prefix at evaluation -------------------------------------------------------------------------------

class PrefixedVLM(VLM):
    """A local VLM that answers with a defense prefix before every question (PAT++'s prefix.json at evaluation).

    The prefix goes in as token ids (`splice_prefix`), exactly as it was tuned. A soft prefix (`embeddings` [n, D],
    defense.soft) goes in as its placeholder ids, whose input embeddings a hook on the embedding layer replaces by
    the tuned vectors whenever the whole spliced prompt is embedded (the prompt pass of generation, a loss), so
    positions, masks and M-RoPE indices are those of any prompt. The name is the model's unless given; the identity
    gains the prefix, so results with and without it never mix; `method` names the defense that tuned it in
    reports."""

    def __init__(self, vlm: HFVLM, prefix_ids: Sequence[int], name: str | None = None, embeddings=None,
                 method: str = "PAT++"):
        if not isinstance(vlm, HFVLM):
            raise ValueError(f"defense prefix: {type(vlm).__name__} gives no token ids to splice a prefix into; "
                             f"PAT++ needs a local model (model=vlm/hf or model=vlm/embedded)")
        self.vlm, self.prefix_ids = vlm, [int(t) for t in prefix_ids]
        vocabulary = vlm.model.get_input_embeddings().num_embeddings
        if not self.prefix_ids or max(self.prefix_ids) >= vocabulary or min(self.prefix_ids) < 0:
            raise ValueError(f"defense prefix: expected token ids in [0, {vocabulary}), got {self.prefix_ids}")
        self.embeddings = None if embeddings is None else _check_embeddings(embeddings, vlm, len(self.prefix_ids))
        self.name, self.batch_size, self.method = name or vlm.name, vlm.batch_size, method
        self._rows: tuple[list[int], int] | None = None  # (prefix starts, spliced length) of the batch in flight

    def answer(self, clips: Sequence[Frames], questions: Sequence[str]) -> list[str]:
        with self._soft():
            return self.vlm.answer_encoded(clips, questions, self._encode)

    def answer_loss(self, clips: Sequence[Frames], questions: Sequence[str], answers: Sequence[str]):
        with self._soft():
            batch = self._encode(clips, questions, answers)
            return self.vlm.loss_from_embeds(batch, self.vlm.embed(batch))

    def _encode(self, clips, questions, answers=None) -> EncodedBatch:
        """The wrapped model's encoding with the prefix spliced in before each question."""
        batch, starts = splice_prefix(self.vlm.encode(clips, questions, answers), self.prefix_ids)
        self._rows = (starts, batch.inputs["input_ids"].shape[1])
        return batch

    @contextmanager
    def _soft(self):
        """While answering: the soft prefix's vectors in place of its placeholders' embeddings (nothing for ids)."""
        if self.embeddings is None:
            yield
            return
        embeddings, n = self.embeddings, len(self.prefix_ids)

        def replace(module, inputs, output):
            if self._rows is None or output.dim() != 3 or output.shape[1] != self._rows[1]:
                return output  # a generation step after the prompt: one new token
            output = output.clone()
            for i, start in enumerate(self._rows[0]):
                output[i, start:start + n] = embeddings.to(output.device, output.dtype)
            return output

        handle = self.vlm.model.get_input_embeddings().register_forward_hook(replace)
        try:
            yield
        finally:
            handle.remove()
            self._rows = None

    def identity(self) -> dict:
        soft = {} if self.embeddings is None else {"defense_prefix_embeddings": _digest(self.embeddings)}
        return {**self.vlm.identity(), "defense_prefix_ids": self.prefix_ids, **soft}


def _check_embeddings(embeddings, vlm: HFVLM, length: int):
    """A soft prefix's vectors as a float tensor [length, D] of the model's embedding width."""
    import torch

    table = vlm.model.get_input_embeddings().weight
    vectors = torch.as_tensor(embeddings, dtype=torch.float32)
    if vectors.shape != (length, table.shape[1]):
        raise ValueError(f"defense prefix: expected soft embeddings [{length}, {table.shape[1]}] (one vector of the "
                         f"model's embedding width per prefix token), got {tuple(vectors.shape)}")
    return vectors.detach()


def _digest(vectors) -> str:
    """A short fingerprint of a soft prefix's vectors (for a run's identity)."""
    import hashlib

    return hashlib.sha256(vectors.float().numpy().tobytes()).hexdigest()[:16]


class PrefixObjective(ControlObjective):
    """PAT++'s objective: alpha * L_bgn(prefix) + (1 - alpha) * L_hard(prefix) on fixed benign and hard examples of a
    frozen model. Either set may be empty (its term is then dropped, and the other weighs 1). `chunk` bounds the
    number of sequences in one forward pass when many candidate prefixes are scored."""

    def __init__(self, vlm: HFVLM, benign: Examples, hard: Examples, alpha: float = 0.6, chunk: int = 64):
        if not 0.0 <= float(alpha) <= 1.0:
            raise ValueError(f"defense.alpha: expected a weight in [0, 1], got {alpha}")
        if len(benign) + len(hard) == 0:
            raise ValueError("examples: no benign and no hard examples; expected at least one")
        self.alpha, self.benign, self.hard = float(alpha), benign, hard
        weights = {"benign": float(alpha), "hard": 1.0 - float(alpha)} if len(benign) and len(hard) else \
            {"benign": 1.0, "hard": 1.0}
        super().__init__(vlm, {"benign": Part(benign, weights["benign"]), "hard": Part(hard, weights["hard"])},
                         "prefix", chunk)


# ---- prefix.json ------------------------------------------------------------------------------------------------

def save_prefix(path: str | os.PathLike, ids: Sequence[int], tokenizer, **extra) -> Path:
    """Write the prefix (token ids and text) and `extra` facts (loss, step, model) atomically as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"text": tokenizer.decode(list(ids)), "ids": [int(t) for t in ids], **extra}
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(record, indent=1))
    os.replace(partial, path)
    return path


def load_prefix(path: str | os.PathLike, tokenizer=None) -> dict:
    """Read a prefix.json; with a tokenizer, check its ids are that tokenizer's and decode to its text."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"defense.prefix_path: no prefix file at {path}; expected the {PREFIX_FILE} that "
                                f"task=train defense=pat++ writes")
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not JSON ({error.msg} at line {error.lineno}); expected a {PREFIX_FILE}") from None
    ids = record.get("ids") if isinstance(record, dict) else None
    if not isinstance(ids, list) or not ids or not all(isinstance(t, int) and t >= 0 for t in ids):
        raise ValueError(f"{path}: expected 'ids', a non-empty list of token ids, got {ids!r}")
    vectors = record.get("embeddings")
    if vectors is not None and not (isinstance(vectors, list) and len(vectors) == len(ids) and all(
            isinstance(v, list) and v and len(v) == len(vectors[0]) and all(isinstance(x, (int, float)) for x in v)
            for v in vectors)):
        raise ValueError(f"{path}: 'embeddings' of a soft prefix: expected {len(ids)} equal-length lists of numbers "
                         f"(one vector per token id)")
    if tokenizer is not None:
        if max(ids) >= len(tokenizer):
            raise ValueError(f"{path}: token id {max(ids)} is outside this model's vocabulary ({len(tokenizer)} "
                             f"tokens); was the prefix tuned for another model?")
        if tokenizer.decode(ids) != record.get("text"):
            raise ValueError(f"{path}: its ids decode to {tokenizer.decode(ids)!r} with this model's tokenizer, not "
                             f"to its text {record.get('text')!r}; was the prefix tuned for another model?")
    return record


# ---- the tuning loop --------------------------------------------------------------------------------------------

@dataclass
class GCGSettings:
    """How GCG searches: steps, prefix length (tokens), top-k tokens per position, single-swap candidates per
    step, and the seed of the candidates' draws (each step's draws follow from seed and step, so a resumed run
    draws what an unbroken one would have)."""

    steps: int = 100
    prefix_length: int = 20
    top_k: int = 256
    num_candidates: int = 128
    seed: int = 0

    def __post_init__(self):
        for name in ("steps", "prefix_length", "top_k", "num_candidates"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"defense.{name}: expected a positive integer, got {value!r}")


def resume_state(path: Path, tokenizer, settings: dict, facts: dict, needs: Sequence[str]) -> dict | None:
    """The state a tuning loop left in `path` (a prefix.json), or None when there is none; a state tuned with other
    settings or facts (all but `steps`), or without the keys `needs`, is refused."""
    if not path.exists():
        return None
    record = load_prefix(path, tokenizer)
    stored = {**record.get("settings", {}), **record.get("facts", {})}
    for key, value in json.loads(json.dumps({**settings, **facts})).items():
        if key != "steps" and stored.get(key) != value:
            raise ValueError(f"{path}: tuned with {key}={stored.get(key)!r}, this run has {key}={value!r}; "
                             f"resume with the same settings or write to another directory")
    missing = [key for key in needs if key not in record]
    if missing:
        raise ValueError(f"{path}: no {', '.join(repr(k) for k in missing)}; expected a {PREFIX_FILE} written by this "
                         f"defense's tuning (use another output directory)")
    return record


def progress_note(bar, note: str) -> None:
    """One step of a tuning loop's progress display, with `note` (loss, prefix) beside it."""
    if hasattr(bar, "set_postfix_str"):
        bar.set_postfix_str(note)
        bar.update(1)
    else:
        bar.update(1, note=note)


def tune_prefix(objective: PrefixObjective, settings: GCGSettings, out_dir: str | os.PathLike,
                progress: str = "auto", facts: dict | None = None) -> dict:
    """Tune a defense prefix by GCG and keep it in out_dir/prefix.json, rewritten (atomically) after every step:
    the kept prefix (the best so far: a step never raises its loss), its loss and both terms, the step reached,
    the loss history, the settings and `facts` (what the prefix was tuned on: model identity, alpha, hard
    target...). A run that finds a prefix.json there resumes at its step from its prefix when its settings and
    facts are the same, and refuses to mix otherwise. Returns the final record."""
    import torch

    from lanevil_train.progress import progress_counter

    tokenizer = objective.vlm.processor.tokenizer
    allowed = allowed_tokens(tokenizer, objective.vlm.model.get_input_embeddings().num_embeddings)
    path = Path(out_dir) / PREFIX_FILE
    settings_record = dict(vars(settings))
    facts = dict(facts or {}, alpha=float(objective.alpha))
    record = resume_state(path, tokenizer, settings_record, facts, ("step", "history", "terms"))
    if record is not None:
        prefix, step, history = list(record["ids"]), int(record["step"]), list(record["history"])
        terms = record["terms"]
    else:
        prefix, step = initial_prefix(tokenizer, settings.prefix_length, allowed), 0
        history, terms = [objective.loss(prefix)], objective.terms(prefix)
        _save_state(path, prefix, tokenizer, step, history, terms, settings_record, facts)
    bar = progress_counter(settings.steps, initial=min(step, settings.steps), desc="PAT++ prefix", unit="step",
                           mode=progress)
    while step < settings.steps:
        generator = torch.Generator().manual_seed(settings.seed * 1_000_003 + step)
        result = gcg_step(objective, prefix, allowed, tokenizer, settings.top_k, settings.num_candidates, generator,
                          loss=history[-1])
        prefix, step = result.prefix, step + 1
        history.append(result.loss)
        if result.improved:  # a kept prefix keeps its terms
            terms = objective.terms(prefix)
        _save_state(path, prefix, tokenizer, step, history, terms, settings_record, facts)
        progress_note(bar, f"loss {result.loss:.4f} | prefix {tokenizer.decode(prefix)!r}")
    bar.close()
    return load_prefix(path, tokenizer)


def _save_state(path: Path, prefix, tokenizer, step: int, history: list[float], terms: dict, settings: dict,
                facts: dict) -> None:
    save_prefix(path, prefix, tokenizer, loss=history[-1], terms=terms, step=step, history=history,
                settings=settings, facts=facts)


# ---- the soft variant -------------------------------------------------------------------------------------------

SOFT_STATE = "soft_state.pt"


@dataclass
class SoftSettings:
    """The continuous variant (defense.soft): Adam steps on n free input vectors at the prefix's place, started
    from the embeddings of "! ! ! ...", with learning rate `lr`."""

    steps: int = 100
    prefix_length: int = 20
    lr: float = 0.01
    seed: int = 0

    def __post_init__(self):
        for name in ("steps", "prefix_length"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"defense.{name}: expected a positive integer, got {value!r}")
        if not isinstance(self.lr, (int, float)) or isinstance(self.lr, bool) or not self.lr > 0:
            raise ValueError(f"defense.soft_lr: expected a learning rate > 0, got {self.lr!r}")


def tune_soft_prefix(objective: PrefixObjective, settings: SoftSettings, out_dir: str | os.PathLike,
                     progress: str = "auto", facts: dict | None = None) -> dict:
    """Tune a soft defense prefix: the same objective and place as PAT++'s discrete prefix, its n input vectors
    free (prompt tuning, Lester et al. 2021, as peft's PromptTuning learns them, but spliced before the question
    where PAT++ puts its tokens rather than before the whole input). Full-batch Adam over the objective's examples.
    out_dir/prefix.json holds the placeholder ids ("! ! ! ...") and the best vectors scored so far ("embeddings",
    what task=evaluate applies) with their loss and terms, and the loss history; out_dir/soft_state.pt the current
    vectors and Adam's state; both are written atomically after every step, so a stopped run resumes exactly.
    Returns the final record."""
    import torch

    from lanevil_train.progress import progress_counter

    tokenizer = objective.vlm.processor.tokenizer
    embedding = objective.vlm.model.get_input_embeddings()
    out = Path(out_dir)
    path, state_path = out / PREFIX_FILE, out / SOFT_STATE
    settings_record = dict(vars(settings))
    facts = dict(facts or {}, alpha=float(objective.alpha), soft=True)
    record = resume_state(path, tokenizer, settings_record, facts, ("step", "history", "terms", "embeddings"))
    ids = initial_prefix(tokenizer, settings.prefix_length, allowed_tokens(tokenizer, embedding.num_embeddings))
    vectors = (embedding.weight[ids].detach().float() * embed_scale(embedding)).clone()
    state, step, history, best = None, 0, [], None
    if record is not None:
        if not state_path.is_file():
            raise ValueError(f"{path}: the soft prefix's tuning state {state_path} is missing; use another directory")
        state = torch.load(state_path, weights_only=True)
        vectors, step, history = state["vectors"], int(state["step"]), list(record["history"])
        best = (float(record["loss"]), torch.tensor(record["embeddings"]), record["terms"])
    vectors.requires_grad_(True)
    optimizer = torch.optim.Adam([vectors], lr=settings.lr)
    if state is not None:
        optimizer.load_state_dict(state["optimizer"])
    bar = progress_counter(settings.steps, initial=min(step, settings.steps), desc="PAT++ soft prefix", unit="step",
                           mode=progress)
    while step < settings.steps:
        loss, terms = objective.loss_with_embeds(ids, vectors)
        value = float(loss.detach())
        if best is None or value < best[0]:  # the vectors just scored, before this step moves them
            best = (value, vectors.detach().clone(), terms)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        step += 1
        history.append(value)
        buffer = io.BytesIO()
        torch.save({"vectors": vectors.detach().clone(), "optimizer": optimizer.state_dict(), "step": step}, buffer)
        atomic_write_bytes(state_path, buffer.getvalue())  # the state first: prefix.json never runs ahead of it
        save_prefix(path, ids, tokenizer, loss=best[0], terms=best[2], step=step, history=history,
                    settings=settings_record, facts=facts, soft=True, embeddings=best[1].tolist())
        progress_note(bar, f"loss {value:.4f} (best {best[0]:.4f})")
    bar.close()
    return load_prefix(path, tokenizer)
