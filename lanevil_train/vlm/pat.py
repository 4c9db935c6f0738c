"""PAT++ (the paper's §4.2): a defense prefix of n discrete tokens before the question, tuned by greedy coordinate
gradient (GCG) while the model's weights stay frozen.

The prefix minimises  alpha * L_bgn + (1 - alpha) * L_hard:
  * L_bgn, on benign examples: the NLL of the reference answer with the prefix;
  * L_hard, on hard examples: the NLL of RES_GOAL ("I will focus on the factors affecting the road"), as the paper
    writes it, or RES_GOAL followed by the reference answer (`hard_target="goal_then_answer"`).
Each term is the mean over its examples of a sample's mean NLL per target token (`HFVLM.loss_from_embeds`).

The prefix is spliced into the token ids (`splice_prefix`) right before each question's first token: after the
image tokens in every family whose chat template puts the frames first, and before the question (and so before
the video) in the embedded VLM's question-first template. Position ids, attention masks and M-RoPE indices are
then recomputed from the spliced ids as for any prompt, so the prefix is an ordinary part of the text.

GCG (Zou et al. 2023, as PAT and nanogcg run it): the gradient of the loss w.r.t. a one-hot matrix of the prefix
tokens (one_hot @ embedding matrix spliced into the detached input embeddings); per position the top-k tokens of
minus that gradient among the allowed ones (`allowed_tokens`: decode to printable ASCII, never special or added
tokens); a batch of single-token swaps spread over the positions, those that do not re-tokenise to the prefix's
length dropped; the swaps' losses evaluated in chunks; the best kept only if it lowers the loss.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from lanevil_train.vlm.base import VLM, Frames
from lanevil_train.vlm.hf import IGNORE_INDEX, EncodedBatch, HFVLM

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


# ---- the prefix in the token ids --------------------------------------------------------------------------------

def splice_prefix(batch: EncodedBatch, prefix_ids) -> tuple[EncodedBatch, list[int]]:
    """The batch with `prefix_ids` inserted right before each sample's question, and where each prefix starts.

    `prefix_ids`: one prefix [n] for every sample, or one per sample [B, n]. Every [B, T] tensor of the inputs
    grows by n: input_ids get the prefix, attention_mask ones, any other (token types) zeros; labels get
    IGNORE_INDEX there, and the question and answer spans move by n."""
    import torch

    ids = batch.inputs["input_ids"]
    rows, length = ids.shape
    prefix = torch.as_tensor(prefix_ids, dtype=ids.dtype, device=ids.device)
    if prefix.dim() == 1:
        prefix = prefix.unsqueeze(0).expand(rows, -1)
    if prefix.dim() != 2 or prefix.shape[0] != rows or prefix.shape[1] == 0:
        raise ValueError(f"prefix_ids: expected [n] or [{rows}, n] token ids with n >= 1, got shape "
                         f"{tuple(prefix.shape)}")
    starts = [start for start, _ in batch.question_spans]

    def grow(tensor, fill):
        pieces = [torch.cat([tensor[i, :s], fill[i] if torch.is_tensor(fill) else
                             tensor.new_full((prefix.shape[1],), fill), tensor[i, s:]]) for i, s in enumerate(starts)]
        return torch.stack(pieces)

    inputs = {}
    for key, value in batch.inputs.items():
        if key == "input_ids":
            inputs[key] = grow(value, prefix)
        elif torch.is_tensor(value) and not torch.is_floating_point(value) and tuple(value.shape) == (rows, length):
            inputs[key] = grow(value, 1 if key == "attention_mask" else 0)
        else:
            inputs[key] = value
    n = prefix.shape[1]
    moved = lambda spans: None if spans is None else [(a + n, b + n) for a, b in spans]  # noqa: E731
    spliced = EncodedBatch(inputs=inputs, question_spans=moved(batch.question_spans),
                           answer_spans=moved(batch.answer_spans),
                           labels=None if batch.labels is None else grow(batch.labels, IGNORE_INDEX))
    return spliced, starts


def allowed_tokens(tokenizer, vocab_size: int):
    """A bool mask [vocab_size] of the tokens a prefix may hold: decoded alone they are non-empty printable ASCII
    (letters, digits, punctuation, spaces), and they are neither special nor added tokens (image, video, turn
    markers)."""
    import torch

    banned = set(tokenizer.all_special_ids) | set(getattr(tokenizer, "added_tokens_decoder", {}) or {})
    mask = torch.zeros(vocab_size, dtype=torch.bool)
    for token in range(min(vocab_size, len(tokenizer))):
        if token in banned:
            continue
        text = tokenizer.decode([token])
        mask[token] = bool(text.strip()) and all(32 <= ord(ch) < 127 for ch in text)
    if not mask.any():
        raise ValueError("tokenizer: no token decodes to printable ASCII; a defense prefix cannot be formed")
    return mask


def initial_prefix(tokenizer, length: int, allowed) -> list[int]:
    """The prefix "! ! ! ..." of `length` tokens, as GCG and PAT start: the tokenisation of that text when it has
    exactly `length` allowed tokens, else the "!" token repeated."""
    if length < 1:
        raise ValueError(f"defense.prefix_length: expected a positive number of tokens, got {length}")
    ids = tokenizer(" ".join(["!"] * length), add_special_tokens=False)["input_ids"]
    if len(ids) == length and all(allowed[t] for t in ids):
        return list(ids)
    bang = tokenizer("!", add_special_tokens=False)["input_ids"]
    if len(bang) != 1 or not allowed[bang[0]]:
        raise ValueError("tokenizer: '!' is not one allowed token; cannot form the initial prefix '! ! ! ...'")
    return bang * length


def retokenises(tokenizer, ids: Sequence[int]) -> bool:
    """Whether the decoded prefix re-tokenises to as many tokens as it has (GCG's filter)."""
    text = tokenizer.decode(list(ids))
    return len(tokenizer(text, add_special_tokens=False)["input_ids"]) == len(ids)


class PrefixedVLM(VLM):
    """A local VLM that answers with a defense prefix before every question (PAT++'s prefix.json at evaluation).

    The prefix goes in as token ids (`splice_prefix`), exactly as it was tuned; the name is the model's unless
    given; the identity gains the prefix, so results with and without it never mix."""

    def __init__(self, vlm: HFVLM, prefix_ids: Sequence[int], name: str | None = None):
        if not isinstance(vlm, HFVLM):
            raise ValueError(f"defense prefix: {type(vlm).__name__} gives no token ids to splice a prefix into; "
                             f"PAT++ needs a local model (model=vlm/hf or model=vlm/embedded)")
        self.vlm, self.prefix_ids = vlm, [int(t) for t in prefix_ids]
        vocabulary = vlm.model.get_input_embeddings().num_embeddings
        if not self.prefix_ids or max(self.prefix_ids) >= vocabulary or min(self.prefix_ids) < 0:
            raise ValueError(f"defense prefix: expected token ids in [0, {vocabulary}), got {self.prefix_ids}")
        self.name, self.batch_size = name or vlm.name, vlm.batch_size

    def answer(self, clips: Sequence[Frames], questions: Sequence[str]) -> list[str]:
        return self.vlm.answer_encoded(clips, questions, self._encode)

    def answer_loss(self, clips: Sequence[Frames], questions: Sequence[str], answers: Sequence[str]):
        batch = self._encode(clips, questions, answers)
        return self.vlm.loss_from_embeds(batch, self.vlm.embed(batch))

    def _encode(self, clips, questions, answers=None) -> EncodedBatch:
        """The wrapped model's encoding with the prefix spliced in before each question."""
        return splice_prefix(self.vlm.encode(clips, questions, answers), self.prefix_ids)[0]

    def identity(self) -> dict:
        return {**self.vlm.identity(), "defense_prefix_ids": self.prefix_ids}


# ---- the objective ----------------------------------------------------------------------------------------------

@dataclass
class Examples:
    """Clips, questions and the target each answer should be (a reference answer or RES_GOAL)."""

    clips: Sequence[Frames]
    questions: Sequence[str]
    targets: Sequence[str]

    def __post_init__(self):
        if not (len(self.clips) == len(self.questions) == len(self.targets)):
            raise ValueError(f"examples: {len(self.clips)} clips, {len(self.questions)} questions and "
                             f"{len(self.targets)} targets; expected as many of each")

    def __len__(self) -> int:
        return len(self.clips)


@dataclass
class PrefixObjective:
    """alpha * L_bgn(prefix) + (1 - alpha) * L_hard(prefix) on fixed benign and hard examples of a frozen model.

    Either set may be empty (its term is then dropped, and the other weighs 1). `chunk` bounds the number of
    sequences in one forward pass when many candidate prefixes are scored."""

    vlm: HFVLM
    benign: Examples
    hard: Examples
    alpha: float = 0.6
    chunk: int = 64
    _encoded: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        if not 0.0 <= float(self.alpha) <= 1.0:
            raise ValueError(f"defense.alpha: expected a weight in [0, 1], got {self.alpha}")
        if len(self.benign) + len(self.hard) == 0:
            raise ValueError("examples: no benign and no hard examples; expected at least one")
        if int(self.chunk) < 1:
            raise ValueError(f"defense.chunk: expected a positive number of sequences per pass, got {self.chunk}")

    def weights(self) -> dict[str, float]:
        """The weight of each non-empty term."""
        if not len(self.hard):
            return {"benign": 1.0}
        if not len(self.benign):
            return {"hard": 1.0}
        return {"benign": float(self.alpha), "hard": 1.0 - float(self.alpha)}

    def _batch(self, part: str, copies: int) -> EncodedBatch:
        """The part's examples encoded `copies` times over (for `copies` candidates at once), cached."""
        key = (part, copies)
        if key not in self._encoded:
            examples = getattr(self, part)
            self._encoded[key] = self.vlm.encode(list(examples.clips) * copies, list(examples.questions) * copies,
                                                 list(examples.targets) * copies)
        return self._encoded[key]

    def terms(self, prefix_ids: Sequence[int]) -> dict[str, float]:
        """L_bgn and L_hard (each the mean over its examples) for one prefix."""
        import torch

        with torch.no_grad():
            return {part: float(self._part_losses(part, [list(prefix_ids)]).mean()) for part in self.weights()}

    def loss(self, prefix_ids: Sequence[int]) -> float:
        """The weighted loss of one prefix."""
        return float(self.losses([list(prefix_ids)])[0])

    def losses(self, candidates: Sequence[Sequence[int]]):
        """The weighted loss of each candidate prefix [C], scored in chunks of at most `chunk` sequences."""
        import torch

        with torch.no_grad():
            total = 0
            for part, weight in self.weights().items():
                total = total + weight * self._part_losses(part, candidates).mean(dim=1)
        return total

    def _part_losses(self, part: str, candidates: Sequence[Sequence[int]]):
        """Per candidate and example: the sample's mean target NLL [C, N] with that candidate spliced in."""
        import torch

        examples = len(getattr(self, part))
        per_pass = min(max(1, int(self.chunk) // examples), len(candidates))
        rows = []
        for first in range(0, len(candidates), per_pass):
            group = [list(c) for c in candidates[first:first + per_pass]]
            used = len(group)
            group += [group[-1]] * (per_pass - used)  # a short last group padded: one batch size, one encoding
            prefixes = torch.tensor(group).repeat_interleave(examples, dim=0)
            spliced, _ = splice_prefix(self._batch(part, per_pass), prefixes)
            nll = self.vlm.loss_from_embeds(spliced, self.vlm.embed(spliced))
            rows.append(nll.view(per_pass, examples)[:used])
        return torch.cat(rows)

    def gradient(self, prefix_ids: Sequence[int]):
        """The loss of `prefix_ids` and its gradient [n, V] w.r.t. the one-hot matrix of the prefix's tokens."""
        import torch

        embedding = self.vlm.model.get_input_embeddings()
        weights_matrix = embedding.weight
        one_hot = torch.zeros(len(prefix_ids), weights_matrix.shape[0], dtype=weights_matrix.dtype,
                              device=weights_matrix.device)
        one_hot[torch.arange(len(prefix_ids)), torch.as_tensor(list(prefix_ids))] = 1.0
        one_hot.requires_grad_(True)
        prefix_embeds = one_hot @ weights_matrix * getattr(embedding, "embed_scale", 1.0)  # scaled tables (Gemma3)
        total = 0.0
        for part, weight in self.weights().items():
            spliced, starts = splice_prefix(self._batch(part, 1), list(prefix_ids))
            embeds = self.vlm.embed(spliced).detach()
            rows = [torch.cat([embeds[i, :s], prefix_embeds, embeds[i, s + len(prefix_ids):]])
                    for i, s in enumerate(starts)]
            nll = self.vlm.loss_from_embeds(spliced, torch.stack(rows))
            total = total + weight * nll.mean()
        (grad,) = torch.autograd.grad(total, one_hot)
        return float(total.detach()), grad


# ---- greedy coordinate gradient ---------------------------------------------------------------------------------

@dataclass
class StepResult:
    """One GCG step: the prefix kept, its loss, whether a candidate improved it, and how many were scored."""

    prefix: list[int]
    loss: float
    improved: bool
    candidates: int


def sample_candidates(prefix: Sequence[int], gradient, allowed, top_k: int, count: int, generator) -> list[list[int]]:
    """`count` single-token swaps of `prefix`: position i % n for the i-th (spread over every position), the new
    token drawn uniformly from that position's top-k allowed tokens by minus the gradient; no swap to the same
    token, no duplicates."""
    import torch

    n = len(prefix)
    scores = (-gradient.float()).masked_fill(~allowed.to(gradient.device), float("-inf"))
    k = min(int(top_k), int(allowed.sum()))
    top = scores.topk(k, dim=1).indices.cpu()
    seen, out = set(), []
    picks = torch.randint(0, k, (count,), generator=generator)
    for i in range(count):
        position = i % n
        token = int(top[position, int(picks[i])])
        if token == prefix[position] or (position, token) in seen:
            continue
        seen.add((position, token))
        out.append([*prefix[:position], token, *prefix[position + 1:]])
    return out


def gcg_step(objective: PrefixObjective, prefix: Sequence[int], allowed, tokenizer, top_k: int = 256,
             num_candidates: int = 128, generator=None, loss: float | None = None) -> StepResult:
    """One greedy coordinate gradient step from `prefix`; the kept prefix's loss never rises. `loss`: the prefix's
    `objective.losses` value when already known (scored as the candidates are, so they compare exactly)."""
    import torch

    generator = generator if generator is not None else torch.Generator().manual_seed(0)
    _, gradient = objective.gradient(prefix)
    if loss is None:
        loss = float(objective.losses([list(prefix)])[0])
    candidates = [c for c in sample_candidates(prefix, gradient, allowed, top_k, num_candidates, generator)
                  if retokenises(tokenizer, c)]
    if not candidates:
        return StepResult(list(prefix), loss, False, 0)
    losses = objective.losses(candidates)
    best = int(torch.argmin(losses))
    if float(losses[best]) < loss:
        return StepResult(list(candidates[best]), float(losses[best]), True, len(candidates))
    return StepResult(list(prefix), loss, False, len(candidates))


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
    if path.exists():
        record = load_prefix(path, tokenizer)
        stored = {**record.get("settings", {}), **record.get("facts", {})}
        for key, value in json.loads(json.dumps({**settings_record, **facts})).items():
            if key != "steps" and stored.get(key) != value:
                raise ValueError(f"{path}: tuned with {key}={stored.get(key)!r}, this run has {key}={value!r}; "
                                 f"resume with the same settings or write to another directory")
        if not (isinstance(record.get("step"), int) and isinstance(record.get("history"), list)
                and isinstance(record.get("terms"), dict)):
            raise ValueError(f"{path}: no 'step', 'history' and 'terms'; expected a prefix.json written by "
                             f"tune_prefix (use another output directory)")
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
        note = f"loss {result.loss:.4f} | prefix {tokenizer.decode(prefix)!r}"
        if hasattr(bar, "set_postfix_str"):
            bar.set_postfix_str(note)
            bar.update(1)
        else:
            bar.update(1, note=note)
    bar.close()
    return load_prefix(path, tokenizer)


def _save_state(path: Path, prefix, tokenizer, step: int, history: list[float], terms: dict, settings: dict,
                facts: dict) -> None:
    save_prefix(path, prefix, tokenizer, loss=history[-1], terms=terms, step=step, history=history,
                settings=settings, facts=facts)
