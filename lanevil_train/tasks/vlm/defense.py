"""Textual defenses of a VLM: PAT++ (defense=pat++) tunes a defense prefix for a trained, frozen VLM (discrete
tokens, or with defense.soft continuous vectors); PAT (defense=pat, Mo et al. 2024) tunes one against an attack
suffix tuned at the same time; Self-Reminder (defense=self_reminder) wraps every question in two reminders and needs
no training. defense=mida fine-tunes with AAM++ on the frames first (tasks/vlm/train.py), then tunes PAT++ for the
fine-tuned model.

    python -m lanevil_train task=train model=vlm/hf model.path=RUN/model data.size=[64,112] defense=pat++
    python -m lanevil_train task=evaluate model=vlm/hf model.path=RUN/model defense=pat++ \\
        defense.prefix_path=PAT_RUN/prefix.json task.suite=synthetic
    python -m lanevil_train task=evaluate model=vlm/hf model.path=RUN/model defense=self_reminder task.suite=synthetic

task=train with defense=self_reminder only tests the reminded model. task=train with defense=pat++:
  1. checks every defense.* value first;
  2. asks the model `defense.pool_clips` clip variants' questions, spread over the train split (seeds never
     in the test split). Each answer is scored by `defense.hardness`:
     - accuracy: yes/no and choice questions, right or wrong;
     - judge: every question, with the configured judge's score;
     - language: every question, with the answer's own Language score (metrics.vqa.language_per_answer).
     Answers below the mean make hard examples, the rest benign ones, as AAM++ picks them. `defense.examples`
     of each are drawn and written to examples.json, and a resumed run reuses them;
  3. tunes the prefix (vlm/defenses/pat.py) into prefix.json, resuming from it;
  4. with task.test_after_fit, evaluates the model with the prefix on the test clips, as task=evaluate would.
defense=pat draws its examples without asking the model (closed questions of perturbed clips to attack, questions
of clean clips as benign ones) and tunes prefix and attack suffix in turn (vlm/defenses/pat_baseline.py).
"""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig

from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.tasks.builders import build_split, output_dir
from lanevil_train.tasks.vlm.builders import (
    add_defense_to_report,
    build_judge,
    build_vlm,
    check_prompt_model,
    prefixed,
    prompt_defense,
    spread,
    with_prompt_defense,
)
from lanevil_train.tasks.vlm.evaluate import test_vlm
from lanevil_train.vlm.defenses.settings import PromptDefense

EXAMPLES_FILE = "examples.json"


def tune_prompt_defense(cfg: DictConfig) -> float | None:
    """task=train with a textual defense: for pat++ and pat the prefix tuned into the run's prefix.json, for
    self_reminder nothing; then the defended model tested. Returns the test score when tested."""
    defense = prompt_defense(cfg)
    if not defense.tuned:  # self_reminder, nothing to tune: the reminded model tested, as task=evaluate would
        defended = with_prompt_defense(build_vlm(cfg), defense)
        print(f"defense={cfg.defense.name}: nothing to train; the reminders wrap every question")
        if not cfg.task.get("test_after_fit"):
            return None
        return _test(cfg, defended, output_dir(cfg) / "test")
    if cfg.data.name != "clips":
        raise ValueError(f"data: {defense.prompt.upper()} tunes its prefix on the clip suite's train split: use "
                         f"data=clips (got data={cfg.data.name})")
    check_prompt_model(cfg)
    if defense.hardness == "judge" and (cfg.get("judge") is None or cfg.judge.get("_target_") is None):
        raise ValueError("defense.hardness: judge needs a judge (judge=minilm or judge=openai); got judge=none")
    out = output_dir(cfg)
    train_set = build_split(cfg, "train")
    vlm = build_vlm(cfg)
    vlm.model.requires_grad_(False)  # frozen: only the prefix (its one-hot matrix, or its vectors) takes gradients
    tune = _tune_pat if defense.prompt == "pat" else _tune_pat_plus_plus
    record = tune(cfg, defense, vlm, train_set, out)
    shown = f"{len(record['ids'])} soft vectors" if record.get("soft") else repr(record["text"])
    print(f"defense prefix: {shown} (loss {record['history'][0]:.4f} -> {record['history'][-1]:.4f}); "
          f"{out / 'prefix.json'} (evaluate with defense={cfg.defense.name} "
          f"defense.prefix_path={out / 'prefix.json'})")
    if not cfg.task.get("test_after_fit"):
        return None
    return _test(cfg, prefixed(vlm, record, f"{vlm.name}+{cfg.defense.name}"), out / "test")


def _tune_pat_plus_plus(cfg: DictConfig, defense: PromptDefense, vlm, train_set, out: Path) -> dict:
    """PAT++: hard examples found by asking the model, then the prefix tuned by GCG (or, soft, by Adam)."""
    from lanevil_train.vlm.defenses.pat import GCGSettings, PrefixObjective, SoftSettings, tune_prefix, tune_soft_prefix

    judge = build_judge(cfg, out) if defense.hardness == "judge" else None
    choosing = {"model": vlm.identity(), "seed": int(cfg.seed),
                **{key: getattr(defense, key) for key in ("hardness", "hard_target", "examples", "pool_clips")}}
    chosen = choose_examples(vlm, train_set, defense, judge, out / EXAMPLES_FILE, choosing, cfg.progress)
    benign, hard = (examples_of(train_set, [e for e in chosen if e["hard"] == kind]) for kind in (False, True))
    objective = PrefixObjective(vlm, benign, hard, alpha=defense.alpha, chunk=defense.chunk)
    facts = {**choosing, "examples": [[e["index"], e["qa_id"], e["hard"], e["target"]] for e in chosen]}
    if defense.soft:
        soft = SoftSettings(steps=defense.steps, prefix_length=defense.prefix_length, lr=defense.soft_lr,
                            seed=int(cfg.seed))
        return tune_soft_prefix(objective, soft, out, progress=cfg.progress, facts=facts)
    gcg = GCGSettings(steps=defense.steps, prefix_length=defense.prefix_length, top_k=defense.top_k,
                      num_candidates=defense.num_candidates, seed=int(cfg.seed))
    return tune_prefix(objective, gcg, out, progress=cfg.progress, facts=facts)


def _tune_pat(cfg: DictConfig, defense: PromptDefense, vlm, train_set, out: Path) -> dict:
    """PAT: attacked and benign examples drawn from the train split, then prefix and attack suffix in turn."""
    from lanevil_train.vlm.defenses.pat_baseline import PATSettings, tune_pat

    choosing = {"method": "pat", "seed": int(cfg.seed), "examples": defense.examples,
                "pool_clips": defense.pool_clips}
    chosen = choose_pat_examples(train_set, defense, out / EXAMPLES_FILE, choosing)
    attacked = examples_of(train_set, [e for e in chosen if e["attacked"]])
    benign = examples_of(train_set, [e for e in chosen if not e["attacked"]])
    gcg = PATSettings(steps=defense.steps, prefix_length=defense.prefix_length, top_k=defense.top_k,
                      num_candidates=defense.num_candidates, seed=int(cfg.seed),
                      suffix_length=defense.suffix_length)
    facts = {"model": vlm.identity(), **choosing,
             "examples": [[e["index"], e["qa_id"], e["attacked"], e["wrong"]] for e in chosen]}
    return tune_pat(vlm, attacked, [e["wrong"] for e in chosen if e["attacked"]], benign, gcg, defense.alpha,
                    out, chunk=defense.chunk, progress=cfg.progress, facts=facts)


def _stored_examples(path: Path, choosing: dict) -> list[dict] | None:
    """The examples a previous run chose into `path` by the same `choosing`, None when there is no file; a file
    chosen otherwise is refused."""
    if not path.is_file():
        return None
    stored = json.loads(path.read_text())
    for key, value in json.loads(json.dumps(choosing)).items():
        if stored.get("choosing", {}).get(key) != value:
            raise ValueError(f"{path}: examples chosen with {key}={stored.get('choosing', {}).get(key)!r}, this "
                             f"run has {key}={value!r}; resume with the same settings or write to another "
                             f"directory")
    return stored["examples"]


def choose_pat_examples(train_set, defense: PromptDefense, path: Path, choosing: dict) -> list[dict]:
    """PAT's examples, drawn without asking the model: `examples` closed questions of perturbed clip variants to
    attack (each with the wrong answer the attack pushes toward) and `examples` questions of clean variants as
    benign ones, from `pool_clips` variants spread over the train split (seed choosing["seed"]); kept in `path`."""
    import numpy as np

    from lanevil_train.vlm.defenses.pat_baseline import wrong_answer

    stored = _stored_examples(path, choosing)
    if stored is not None:
        return stored
    rng = np.random.default_rng(choosing["seed"])
    perturbed = [i for i in range(len(train_set)) if train_set.clip_meta(i)["severity"] > 0]
    clean = [i for i in range(len(train_set)) if train_set.clip_meta(i)["severity"] == 0]
    attackable, benign = [], []
    for attacked, variants in ((True, perturbed), (False, clean)):
        for index in spread(variants, defense.pool_clips)[:defense.pool_clips]:
            for qa in train_set.qa_for(train_set.clip_meta(index)["base_clip_id"]):
                if attacked and qa["type"] != "open":
                    attackable.append({"index": index, "qa_id": qa["qa_id"], "attacked": True,
                                       "target": qa["answer"], "wrong": wrong_answer(qa, int(rng.integers(3)))})
                elif not attacked:
                    benign.append({"index": index, "qa_id": qa["qa_id"], "attacked": False, "target": qa["answer"],
                                   "wrong": None})
    if not attackable or not benign:
        raise ValueError(f"defense.pool_clips: {defense.pool_clips} clean and perturbed train clips hold "
                         f"{len(benign)} questions and {len(attackable)} closed questions; PAT needs both (raise "
                         f"defense.pool_clips, or train on a split with perturbed clips)")
    chosen = [group[i] for group in (benign, attackable)
              for i in sorted(rng.permutation(len(group))[:defense.examples].tolist())]
    atomic_write_text(path, json.dumps({"choosing": choosing, "examples": chosen}, indent=1))
    return chosen


def _test(cfg: DictConfig, defended, out: Path) -> float:
    """The defended VLM tested as task=evaluate would, its defense named in the report."""
    score = test_vlm(cfg, defended, cfg.task.get("label") or defended.name, out)
    add_defense_to_report(out, defended)
    return score


def choose_examples(vlm, train_set, defense: PromptDefense, judge, path: Path, choosing: dict,
                    progress: str) -> list[dict]:
    """Benign and hard examples of the train split: the answers to the pool's questions scored, those below the
    mean hard; `examples` of each drawn at random (choosing["seed"]). Kept in `path` with `choosing` (what they
    were chosen by), and read back from it when a rerun chooses by the same; a rerun that would choose otherwise
    is refused."""
    import numpy as np

    from lanevil_train.progress import progress_counter
    from lanevil_train.vlm.clips.qa_records import answer_is_correct, prompt_text
    from lanevil_train.vlm.defenses.pat import hard_mask

    stored = _stored_examples(path, choosing)
    if stored is not None:
        return stored
    closed = defense.hardness == "accuracy"
    indices = spread(list(range(len(train_set))), defense.pool_clips)[:defense.pool_clips]
    pool, answers = [], []
    bar = progress_counter(len(indices), desc="PAT++ hard examples", unit="clip", mode=progress)
    for index in indices:
        item = train_set[index]
        qas = [qa for qa in item["qa"] if not closed or qa["type"] in ("yes_no", "choice")]
        if qas:
            frames = [np.asarray(frame, dtype=np.uint8) for frame in item["frames"]]
            answers += vlm.answer([frames] * len(qas), [prompt_text(qa) for qa in qas])
            pool += [(index, qa) for qa in qas]
        bar.update(1)
    bar.close()
    if not pool:
        raise ValueError(f"defense.pool_clips: the {len(indices)} train clips asked have no questions to score "
                         f"by defense.hardness={defense.hardness}")
    if closed:
        scores = [float(bool(answer_is_correct(qa, text))) for (_, qa), text in zip(pool, answers)]
    elif defense.hardness == "language":  # each answer's own Language score against its reference
        from lanevil_train.metrics.vqa import language_per_answer

        per_answer = language_per_answer({str(i): text for i, text in enumerate(answers)},
                                         {str(i): qa["answer"] for i, (_, qa) in enumerate(pool)})
        scores = [per_answer[str(i)] for i in range(len(pool))]
    else:
        judged = judge.score([qa["question"] for _, qa in pool], [qa["answer"] for _, qa in pool], answers)
        kept = [i for i, s in enumerate(judged) if s is not None]
        if len(kept) < len(pool):
            print(f"PAT++: the judge left {len(pool) - len(kept)} of {len(pool)} answers unscored; they are left out")
        if not kept:
            raise ValueError("defense.hardness=judge: the judge scored none of the pool's answers")
        pool, answers, scores = [pool[i] for i in kept], [answers[i] for i in kept], [float(judged[i]) for i in kept]
    hard = hard_mask(scores)
    if not any(hard):
        print(f"PAT++: all {len(scores)} answers of the pool score {scores[0]:g} by {defense.hardness}: no hard "
              f"examples, so the prefix is tuned on benign ones only")
    rng = np.random.default_rng(choosing["seed"])
    chosen = []
    for kind in (False, True):
        members = [i for i, h in enumerate(hard) if h == kind]
        for i in sorted(rng.permutation(members)[:defense.examples].tolist()):
            index, qa = pool[i]
            chosen.append({"index": index, "qa_id": qa["qa_id"], "hard": kind, "score": scores[i],
                           "answer": answers[i], "target": _target(qa, kind, defense.hard_target)})
    atomic_write_text(path, json.dumps({"choosing": choosing, "mean_score": float(np.mean(scores)), "pool": len(pool),
                                        "examples": chosen}, indent=1))
    return chosen


def _target(qa: dict, hard: bool, mode: str) -> str:
    from lanevil_train.vlm.defenses.pat import hard_target

    return hard_target(qa["answer"], mode) if hard else qa["answer"]


def examples_of(train_set, chosen: list[dict]):
    """The chosen examples' frames, prompts and targets (pat.Examples)."""
    import numpy as np

    from lanevil_train.vlm.clips.qa_records import prompt_text
    from lanevil_train.vlm.defenses.gcg import Examples

    clips, questions = [], []
    for example in chosen:
        item = train_set[example["index"]]
        qa = next((q for q in item["qa"] if q["qa_id"] == example["qa_id"]), None)
        if qa is None:
            raise ValueError(f"{EXAMPLES_FILE}: train clip {example['index']} has no QA {example['qa_id']!r}; the "
                             f"train split changed since the examples were chosen: use a new output directory")
        clips.append([np.asarray(frame, dtype=np.uint8) for frame in item["frames"]])
        questions.append(prompt_text(qa))
    return Examples(clips, questions, [example["target"] for example in chosen])
