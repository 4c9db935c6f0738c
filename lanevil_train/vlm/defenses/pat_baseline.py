"""PAT (Mo et al. 2024, "Fight Back Against Jailbreaking via Prompt Adversarial Tuning"), the textual baseline the
paper compares PAT++ with (§5.4), adapted from jailbreaks to illusions.

PAT tunes a defense prefix against an adversary that is tuned at the same time. Each step, as their code alternates
them (rain152/PAT):
  1. the attack: one GCG step (vlm/defenses/gcg.py) on an attack suffix after the question, lowering the NLL of the
     wrong answer (`wrong_answer`: the other of yes/no, another option of a choice question) on the attacked examples,
     which carry the defense prefix as it is;
  2. the defense: one GCG step on the prefix, lowering alpha * L_bgn + (1 - alpha) * L_adv, where L_bgn is the NLL
     of the reference answer on benign examples (prefix, question) and L_adv that of the reference answer on the
     attacked examples with the attack suffix as it now is.
In PAT the attacked prompts' target is a refusal; a driving assistant under attack should answer correctly, so
here it is the reference answer. There is no hard-example split (that is PAT++'s addition): the attacked examples
are closed questions of perturbed clips, the benign ones questions of clean clips, drawn at random. Defaults follow
PAT's scripts (alpha 0.2, top-k 256). Only the defense prefix is applied at evaluation (it is a prefix.json like
PAT++'s); the attack suffix is kept beside it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from lanevil_train.vlm.backends.hf import HFVLM
from lanevil_train.vlm.defenses.gcg import ControlObjective, Examples, Part, allowed_tokens, gcg_step, initial_prefix
from lanevil_train.vlm.defenses.pat import (
    PREFIX_FILE,
    GCGSettings,
    load_prefix,
    progress_note,
    resume_state,
    save_prefix,
)


@dataclass
class PATSettings(GCGSettings):
    """GCG's settings for both controls, and the attack suffix's length (tokens)."""

    suffix_length: int = 20

    def __post_init__(self):
        super().__post_init__()
        if not isinstance(self.suffix_length, int) or isinstance(self.suffix_length, bool) or self.suffix_length < 1:
            raise ValueError(f"defense.suffix_length: expected a positive integer, got {self.suffix_length!r}")


def wrong_answer(qa: dict, pick: int = 0) -> str | None:
    """The answer an attack pushes a closed question toward: "No." for a Yes answer and "Yes." for a No, another
    option of a choice question (the `pick`-th of the wrong ones, cyclically); None for an open question."""
    if qa["type"] == "yes_no":
        return "No." if qa["answer"].strip().lower().startswith("yes") else "Yes."
    if qa["type"] == "choice":
        letter = qa["answer"].split(".", 1)[0]
        others = [choice for choice in qa["choices"] if choice.split(".", 1)[0] != letter]
        return others[pick % len(others)]
    return None


def tune_pat(vlm: HFVLM, attacked: Examples, wrong: Sequence[str], benign: Examples, settings: PATSettings,
             alpha: float, out_dir: str | os.PathLike, chunk: int = 64, progress: str = "auto",
             facts: dict | None = None) -> dict:
    """Alternate PAT's attack and defense GCG steps (module doc) for `settings.steps` steps; the defense prefix,
    its loss and terms, and the attack suffix with its loss, written atomically to out_dir/prefix.json after every
    step. A rerun with more steps resumes from it (with the same settings and facts; others are refused). Returns
    the final record."""
    import torch

    from lanevil_train.progress import progress_counter

    if not 0.0 <= float(alpha) <= 1.0:
        raise ValueError(f"defense.alpha: expected a weight in [0, 1], got {alpha}")
    if len(wrong) != len(attacked):
        raise ValueError(f"wrong: {len(wrong)} wrong answers for {len(attacked)} attacked examples")
    tokenizer = vlm.processor.tokenizer
    allowed = allowed_tokens(tokenizer, vlm.model.get_input_embeddings().num_embeddings)
    path = Path(out_dir) / PREFIX_FILE
    settings_record = dict(vars(settings))
    facts = dict(facts or {}, alpha=float(alpha), method="pat")
    record = resume_state(path, tokenizer, settings_record, facts, ("step", "history", "terms", "attack"))
    if record is not None:
        prefix, suffix, step = list(record["ids"]), list(record["attack"]["ids"]), int(record["step"])
        history, attack_history = list(record["history"]), list(record["attack"]["history"])
    else:
        prefix = initial_prefix(tokenizer, settings.prefix_length, allowed)
        suffix = initial_prefix(tokenizer, settings.suffix_length, allowed, key="defense.suffix_length")
        step, history, attack_history = 0, [], []
    attack = ControlObjective(vlm, {"attack": Part(Examples(attacked.clips, attacked.questions, list(wrong)), 1.0,
                                                   prefix=prefix)}, "suffix", chunk)
    defense = ControlObjective(vlm, {"benign": Part(benign, float(alpha)),
                                     "attacked": Part(attacked, 1.0 - float(alpha), suffix=suffix)}, "prefix", chunk)
    if record is None:
        history, attack_history = [defense.loss(prefix)], [attack.loss(suffix)]
        _save(path, tokenizer, prefix, suffix, step, history, attack_history, defense.terms(prefix),
              settings_record, facts)
    bar = progress_counter(settings.steps, initial=min(step, settings.steps), desc="PAT prefix and attack",
                           unit="step", mode=progress)
    while step < settings.steps:
        generator = torch.Generator().manual_seed(settings.seed * 1_000_003 + step)
        attack.parts["attack"].prefix = prefix
        suffix = gcg_step(attack, suffix, allowed, tokenizer, settings.top_k, settings.num_candidates, generator).prefix
        defense.parts["attacked"].suffix = suffix
        result = gcg_step(defense, prefix, allowed, tokenizer, settings.top_k, settings.num_candidates, generator)
        prefix, step = result.prefix, step + 1
        attack.parts["attack"].prefix = prefix
        history.append(result.loss)
        attack_history.append(attack.loss(suffix))
        _save(path, tokenizer, prefix, suffix, step, history, attack_history, defense.terms(prefix), settings_record,
              facts)
        progress_note(bar, f"defense loss {result.loss:.4f} | attack loss {attack_history[-1]:.4f} | prefix "
                           f"{tokenizer.decode(prefix)!r}")
    bar.close()
    return load_prefix(path, tokenizer)


def _save(path: Path, tokenizer, prefix, suffix, step: int, history: list[float], attack_history: list[float],
          terms: dict, settings: dict, facts: dict) -> None:
    save_prefix(path, prefix, tokenizer, loss=history[-1], terms=terms, step=step, history=history,
                attack={"ids": [int(t) for t in suffix], "text": tokenizer.decode(list(suffix)),
                        "loss": attack_history[-1], "history": attack_history},
                settings=settings, facts=facts)
