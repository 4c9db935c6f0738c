"""Greedy coordinate gradient (GCG) over a slot of discrete tokens spliced into a VLM's prompts: PAT++'s defense
prefix (vlm/defenses/pat.py), and PAT's defense prefix and attack suffix (vlm/defenses/pat_baseline.py), are tuned by
the same steps.

A control is n token ids spliced into the token ids of every example: right before the question (`prefix`: after
the image tokens in every family whose chat template puts the frames first, before the question and so before the
video in the embedded VLM's question-first template) or right after it (`suffix`). Position ids, attention masks
and M-RoPE indices are then computed from the spliced ids as for any prompt, so a control is an ordinary part of
the text.

GCG (Zou et al. 2023, as PAT and nanogcg run it): the gradient of the loss w.r.t. a one-hot matrix of the control's
tokens (one_hot @ embedding matrix spliced into the detached input embeddings); per position the top-k tokens of
minus that gradient among the allowed ones (`allowed_tokens`: decode to printable ASCII, never special or added
tokens); a batch of single-token swaps spread over the positions, those that do not re-tokenise to the control's
length dropped; the swaps' losses evaluated in chunks; the best kept only if it lowers the loss.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

from lanevil_train.vlm.backends.hf import HFVLM, IGNORE_INDEX, EncodedBatch
from lanevil_train.vlm.base import Frames

SLOTS = ("prefix", "suffix")


# ---- controls in the token ids ----------------------------------------------------------------------------------

def splice_prefix(batch: EncodedBatch, prefix_ids) -> tuple[EncodedBatch, list[int]]:
    """The batch with `prefix_ids` inserted right before each sample's question, and where each prefix starts.

    `prefix_ids`: one prefix [n] for every sample, or one per sample [B, n]. Every [B, T] tensor of the inputs
    grows by n: input_ids get the prefix, attention_mask ones, any other (token types) zeros; labels get
    IGNORE_INDEX there, and the question and answer spans move by n."""
    return _splice(batch, prefix_ids, [start for start, _ in batch.question_spans], moves_question=True)


def splice_suffix(batch: EncodedBatch, suffix_ids) -> tuple[EncodedBatch, list[int]]:
    """The batch with `suffix_ids` inserted right after each sample's question (before the rest of its turn), and
    where each suffix starts; as splice_prefix, but the question span stays where it is."""
    return _splice(batch, suffix_ids, [end for _, end in batch.question_spans], moves_question=False)


def _splice(batch: EncodedBatch, ids, starts: list[int], moves_question: bool) -> tuple[EncodedBatch, list[int]]:
    import torch

    input_ids = batch.inputs["input_ids"]
    rows, length = input_ids.shape
    tokens = torch.as_tensor(ids, dtype=input_ids.dtype, device=input_ids.device)
    if tokens.dim() == 1:
        tokens = tokens.unsqueeze(0).expand(rows, -1)
    if tokens.dim() != 2 or tokens.shape[0] != rows or tokens.shape[1] == 0:
        raise ValueError(f"control ids: expected [n] or [{rows}, n] token ids with n >= 1, got shape "
                         f"{tuple(tokens.shape)}")

    def grow(tensor, fill):
        pieces = [torch.cat([tensor[i, :s], fill[i] if torch.is_tensor(fill) else
                             tensor.new_full((tokens.shape[1],), fill), tensor[i, s:]]) for i, s in enumerate(starts)]
        return torch.stack(pieces)

    inputs = {}
    for key, value in batch.inputs.items():
        if key == "input_ids":
            inputs[key] = grow(value, tokens)
        elif torch.is_tensor(value) and not torch.is_floating_point(value) and tuple(value.shape) == (rows, length):
            inputs[key] = grow(value, 1 if key == "attention_mask" else 0)
        else:
            inputs[key] = value
    n = tokens.shape[1]
    moved = lambda spans: None if spans is None else [(a + n, b + n) for a, b in spans]  # noqa: E731
    spliced = EncodedBatch(inputs=inputs,
                           question_spans=moved(batch.question_spans) if moves_question else batch.question_spans,
                           answer_spans=moved(batch.answer_spans),
                           labels=None if batch.labels is None else grow(batch.labels, IGNORE_INDEX))
    return spliced, starts


def allowed_tokens(tokenizer, vocab_size: int):
    """A bool mask [vocab_size] of the tokens a control may hold: decoded alone they are non-empty printable ASCII
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


def initial_prefix(tokenizer, length: int, allowed, key: str = "defense.prefix_length") -> list[int]:
    """The control "! ! ! ..." of `length` tokens, as GCG and PAT start: the tokenisation of that text when it has
    exactly `length` allowed tokens, else the "!" token repeated. `key` names the length's setting in errors."""
    if length < 1:
        raise ValueError(f"{key}: expected a positive number of tokens, got {length}")
    ids = tokenizer(" ".join(["!"] * length), add_special_tokens=False)["input_ids"]
    if len(ids) == length and all(allowed[t] for t in ids):
        return list(ids)
    bang = tokenizer("!", add_special_tokens=False)["input_ids"]
    if len(bang) != 1 or not allowed[bang[0]]:
        raise ValueError("tokenizer: '!' is not one allowed token; cannot form the initial control '! ! ! ...'")
    return bang * length


def retokenises(tokenizer, ids: Sequence[int]) -> bool:
    """Whether the decoded control re-tokenises to as many tokens as it has (GCG's filter)."""
    text = tokenizer.decode(list(ids))
    return len(tokenizer(text, add_special_tokens=False)["input_ids"]) == len(ids)


# ---- the objective ----------------------------------------------------------------------------------------------

@dataclass
class Examples:
    """Clips, questions and the target each answer should be (a reference answer, RES_GOAL, a wrong answer)."""

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
class Part:
    """One weighted term of a control objective: its examples, and the fixed tokens of the other slot that every
    one of them carries (PAT's attack suffix while its defense prefix is tuned, and the reverse)."""

    examples: Examples
    weight: float
    prefix: Sequence[int] | None = None
    suffix: Sequence[int] | None = None


@dataclass
class ControlObjective:
    """sum of weight * (mean over the part's examples of a sample's mean target NLL) over `parts`, the control tuned
    spliced at `slot` of every example of a frozen model. `chunk` bounds the sequences of one forward pass when
    many candidate controls are scored."""

    vlm: HFVLM
    parts: dict[str, Part]
    slot: str = "prefix"
    chunk: int = 64
    _encoded: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        if self.slot not in SLOTS:
            raise ValueError(f"slot: expected one of {', '.join(SLOTS)}, got {self.slot!r}")
        if int(self.chunk) < 1:
            raise ValueError(f"defense.chunk: expected a positive number of sequences per pass, got {self.chunk}")
        self.parts = {name: part for name, part in self.parts.items() if len(part.examples)}
        if not self.parts:
            raise ValueError("examples: every part of the objective is empty; expected at least one example")

    def weights(self) -> dict[str, float]:
        """The weight of each non-empty part."""
        return {name: float(part.weight) for name, part in self.parts.items()}

    def _batch(self, name: str, copies: int) -> EncodedBatch:
        """The part's examples encoded `copies` times over (for `copies` candidates at once), cached."""
        key = (name, copies)
        if key not in self._encoded:
            examples = self.parts[name].examples
            self._encoded[key] = self.vlm.encode(list(examples.clips) * copies, list(examples.questions) * copies,
                                                 list(examples.targets) * copies)
        return self._encoded[key]

    def _spliced(self, name: str, control, copies: int) -> tuple[EncodedBatch, list[int]]:
        """The part's batch (`copies` times over) with its fixed tokens and `control` ([n] or [rows, n]) spliced in:
        the prefix first, then the suffix after the question; where the control starts in each row."""
        part = self.parts[name]
        prefix = control if self.slot == "prefix" else part.prefix
        suffix = control if self.slot == "suffix" else part.suffix
        batch, starts = self._batch(name, copies), None
        if prefix is not None:
            batch, starts = splice_prefix(batch, prefix)
        if suffix is not None:
            batch, after = splice_suffix(batch, suffix)
            starts = after if self.slot == "suffix" else starts
        return batch, starts

    def terms(self, control: Sequence[int]) -> dict[str, float]:
        """Each part's mean loss for one control."""
        import torch

        with torch.no_grad():
            return {name: float(self._part_losses(name, [list(control)]).mean()) for name in self.parts}

    def loss(self, control: Sequence[int]) -> float:
        """The weighted loss of one control."""
        return float(self.losses([list(control)])[0])

    def losses(self, candidates: Sequence[Sequence[int]]):
        """The weighted loss of each candidate control [C], scored in chunks of at most `chunk` sequences."""
        import torch

        with torch.no_grad():
            total = 0
            for name, weight in self.weights().items():
                total = total + weight * self._part_losses(name, candidates).mean(dim=1)
        return total

    def _part_losses(self, name: str, candidates: Sequence[Sequence[int]]):
        """Per candidate and example: the sample's mean target NLL [C, N] with that candidate spliced in."""
        import torch

        examples = len(self.parts[name].examples)
        per_pass = min(max(1, int(self.chunk) // examples), len(candidates))
        rows = []
        for first in range(0, len(candidates), per_pass):
            group = [list(c) for c in candidates[first:first + per_pass]]
            used = len(group)
            group += [group[-1]] * (per_pass - used)  # a short last group padded: one batch size, one encoding
            spliced, _ = self._spliced(name, torch.tensor(group).repeat_interleave(examples, dim=0), per_pass)
            nll = self.vlm.loss_from_embeds(spliced, self.vlm.embed(spliced))
            rows.append(nll.view(per_pass, examples)[:used])
        return torch.cat(rows)

    def gradient(self, control: Sequence[int]):
        """The loss of `control` and its gradient [n, V] w.r.t. the one-hot matrix of the control's tokens."""
        import torch

        embedding = self.vlm.model.get_input_embeddings()
        weights_matrix = embedding.weight
        one_hot = torch.zeros(len(control), weights_matrix.shape[0], dtype=weights_matrix.dtype,
                              device=weights_matrix.device)
        one_hot[torch.arange(len(control)), torch.as_tensor(list(control))] = 1.0
        one_hot.requires_grad_(True)
        total, _ = self.loss_with_embeds(control, one_hot @ weights_matrix * embed_scale(embedding))
        (grad,) = torch.autograd.grad(total, one_hot)
        return float(total.detach()), grad

    def loss_with_embeds(self, control: Sequence[int], control_embeds) -> tuple:
        """The weighted loss (a differentiable scalar) with the control's input embeddings replaced by
        `control_embeds` [n, D], and each part's mean loss (floats): the one-hot gradient's path, and a soft
        prompt's (continuous vectors)."""
        import torch

        total, terms = 0.0, {}
        for name, weight in self.weights().items():
            spliced, starts = self._spliced(name, list(control), 1)
            embeds = self.vlm.embed(spliced).detach()
            rows = [torch.cat([embeds[i, :s], control_embeds.to(embeds.dtype), embeds[i, s + len(control):]])
                    for i, s in enumerate(starts)]
            nll = self.vlm.loss_from_embeds(spliced, torch.stack(rows)).mean()
            terms[name] = float(nll.detach())
            total = total + weight * nll
        return total, terms


def embed_scale(embedding) -> float:
    """The factor an embedding module multiplies its table rows by (Gemma3's scaled embeddings), else 1."""
    return getattr(embedding, "embed_scale", 1.0)


# ---- greedy coordinate gradient ---------------------------------------------------------------------------------

@dataclass
class StepResult:
    """One GCG step: the control kept, its loss, whether a candidate improved it, and how many were scored."""

    prefix: list[int]
    loss: float
    improved: bool
    candidates: int


def sample_candidates(prefix: Sequence[int], gradient, allowed, top_k: int, count: int, generator) -> list[list[int]]:
    """`count` single-token swaps of the control `prefix`: position i % n for the i-th (spread over every position),
    the new token drawn uniformly from that position's top-k allowed tokens by minus the gradient; no swap to the
    same token, no duplicates."""
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


def gcg_step(objective: ControlObjective, prefix: Sequence[int], allowed, tokenizer, top_k: int = 256,
             num_candidates: int = 128, generator=None, loss: float | None = None) -> StepResult:
    """One greedy coordinate gradient step from the control `prefix`; the kept control's loss never rises. `loss`:
    the control's `objective.losses` value when already known (scored as the candidates are, so they compare
    exactly)."""
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
