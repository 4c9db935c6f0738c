"""Textual defenses of a VLM: PAT++ (defense=pat++) tunes a defense prefix for a trained, frozen VLM (discrete
tokens, or with defense.soft continuous vectors); PAT (defense=pat, Mo et al. 2024) tunes one against an attack
suffix tuned at the same time; Self-Reminder (defense=self_reminder) wraps every question in two reminders and needs
no training. defense=mida fine-tunes with AAM++ on the frames first (tasks/vlm_train.py), then tunes PAT++ for the
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

from omegaconf import DictConfig, OmegaConf

from lanevil_train.files.atomic import atomic_write_text

PROMPT_DEFENSES = ("pat++", "pat", "self_reminder")
HARDNESS = ("accuracy", "judge", "language")  # how PAT++ finds hard examples (choose_examples)
TUNED = ("pat++", "pat")  # the prompt defenses whose prefix is tuned into prefix.json
EXAMPLES_FILE = "examples.json"


def is_prompt_defense(cfg: DictConfig) -> bool:
    """Whether cfg.defense is (or has) a textual defense of VLMs (it names a `prompt` method)."""
    return cfg.get("defense") is not None and cfg.defense.get("prompt") is not None


def fine_tunes(defense: DictConfig) -> bool:
    """Whether the defense changes the model's weights: a visual part (a callback or a mixer) that acts during
    fine-tuning (defense=none, aam++, mida ...), not only a prompt for the model as it is (pat++, pat, ...)."""
    return defense.get("prompt") is None or defense.get("callback") is not None or defense.get("mixer") is not None


def prompt_settings(defense: DictConfig) -> dict:
    """defense.* of a prompt defense as plain values, each present and good by config_check's rules; a ValueError
    names the first bad key."""
    from lanevil_train.tasks.config_check import value_problem

    settings = OmegaConf.to_container(defense, resolve=True)
    method = settings.get("prompt")
    gcg = ("alpha", "steps", "prefix_length", "top_k", "num_candidates", "chunk", "examples", "pool_clips")
    keys = ("prompt",) + {"self_reminder": ("before", "after"), "pat": gcg + ("suffix_length",),
                          "pat++": gcg + ("hard_target", "hardness", "soft", "soft_lr")}.get(method, ())
    for key in keys:
        problem = value_problem(f"defense.{key}", settings.get(key))
        if problem is not None:
            raise ValueError(problem)
    return settings


def check_prompt_model(cfg: DictConfig) -> None:
    """A prefix is tuned for a trained local model: model=vlm/hf or vlm/embedded, with model.path or ckpt_path."""
    target = cfg.model.get("_target_")
    if cfg.ckpt_path is None and target != "lanevil_train.vlm.backends.hf.HFVLM":
        raise ValueError(f"model: defense={cfg.defense.name} splices a prefix into a local model's token ids; use "
                         f"model=vlm/hf or model=vlm/embedded (got model._target_={target})")
    if cfg.ckpt_path is None and cfg.model.get("path") is None:
        raise ValueError(f"model.path: defense={cfg.defense.name} tunes a prefix for a trained model; give "
                         f"model.path=RUN/model (task=train model=vlm/embedded writes one) or ckpt_path=...")


def check_prompt_defense(cfg: DictConfig) -> None:
    """task=evaluate, before the model loads: the defense's settings, and for pat++ the prefix to apply and a backend
    it can be spliced into."""
    settings = prompt_settings(cfg.defense)
    if settings["prompt"] in TUNED:
        if cfg.defense.get("prefix_path") is None:
            raise ValueError(f"defense.prefix_path: task=evaluate defense={cfg.defense.name} applies a tuned prefix; "
                             f"give defense.prefix_path=RUN/prefix.json (task=train defense={cfg.defense.name} writes "
                             f"it)")
        check_prompt_model(cfg)


def with_prompt_defense(cfg: DictConfig, vlm):
    """task=evaluate: the VLM with its questions wrapped in the reminders (self_reminder), or with the tuned prefix
    of defense.prefix_path before every question (pat++)."""
    from lanevil_train.vlm.defenses.pat import load_prefix
    from lanevil_train.vlm.defenses.reminder import RemindedVLM

    settings = prompt_settings(cfg.defense)
    name = f"{vlm.name}+{cfg.defense.name}"
    if settings["prompt"] == "self_reminder":
        return RemindedVLM(vlm, settings["before"], settings["after"], name=name)
    check_prompt_defense(cfg)
    return prefixed(vlm, load_prefix(cfg.defense.prefix_path, getattr(getattr(vlm, "processor", None), "tokenizer",
                                                                       None)), name)


def prefixed(vlm, record: dict, name: str):
    """The VLM with a tuned prefix.json `record` before every question (its token ids, or its soft vectors)."""
    from lanevil_train.vlm.defenses.pat import PrefixedVLM

    method = "PAT" if record.get("facts", {}).get("method") == "pat" else "PAT++"
    return PrefixedVLM(vlm, record["ids"], name=name, embeddings=record.get("embeddings"), method=method)


def describe_defense(vlm) -> str | None:
    """A markdown section naming the textual defense a VLM answers with (its prefix, or its reminders), else None."""
    from lanevil_train.vlm.defenses.pat import PrefixedVLM
    from lanevil_train.vlm.defenses.reminder import RemindedVLM

    if isinstance(vlm, PrefixedVLM) and vlm.embeddings is not None:
        return (f"## Defense: {vlm.method} soft prefix\n\nBefore every question, {len(vlm.prefix_ids)} tuned vectors "
                f"of width {vlm.embeddings.shape[1]} in place of the tokens {vlm.prefix_ids}\n")
    if isinstance(vlm, PrefixedVLM):
        text = vlm.vlm.processor.tokenizer.decode(vlm.prefix_ids)
        return (f"## Defense: {vlm.method} prefix\n\nBefore every question, {len(vlm.prefix_ids)} tokens: "
                f"`` {text} ``\n\nToken ids: {vlm.prefix_ids}\n")
    if isinstance(vlm, RemindedVLM):
        return (f"## Defense: Self-Reminder\n\nEvery question between\n\n> {vlm.before}\n\nand\n\n"
                f"> {vlm.after}\n")
    return None


def add_defense_to_report(out: Path, vlm) -> None:
    """Put the defense's section right after the title of out/report.md (when both exist)."""
    report, section = out / "report.md", describe_defense(vlm)
    if section is None or not report.is_file():
        return
    title, _, rest = report.read_text().partition("\n")
    atomic_write_text(report, f"{title}\n\n{section}{rest}")


def tune_prompt_defense(cfg: DictConfig) -> float | None:
    """task=train with a textual defense: for pat++ and pat the prefix tuned into the run's prefix.json, for
    self_reminder nothing; then the defended model tested. Returns the test score when tested."""
    from lanevil_train.tasks.builders import build_split, output_dir
    from lanevil_train.tasks.vlm_evaluate import build_vlm

    settings = prompt_settings(cfg.defense)
    if settings["prompt"] == "self_reminder":  # nothing to tune: the reminded model tested, as task=evaluate would
        defended = with_prompt_defense(cfg, build_vlm(cfg))
        print(f"defense={cfg.defense.name}: nothing to train; the reminders wrap every question")
        if not cfg.task.get("test_after_fit"):
            return None
        return _test(cfg, defended, output_dir(cfg) / "test")
    if cfg.data.name != "clips":
        raise ValueError(f"data: {settings['prompt'].upper()} tunes its prefix on the clip suite's train split: use "
                         f"data=clips (got data={cfg.data.name})")
    check_prompt_model(cfg)
    if settings.get("hardness") == "judge" and (cfg.get("judge") is None or cfg.judge.get("_target_") is None):
        raise ValueError("defense.hardness: judge needs a judge (judge=minilm or judge=openai); got judge=none")
    out = output_dir(cfg)
    train_set = build_split(cfg, "train")
    vlm = build_vlm(cfg)
    vlm.model.requires_grad_(False)  # frozen: only the prefix (its one-hot matrix, or its vectors) takes gradients
    tune = _tune_pat if settings["prompt"] == "pat" else _tune_pat_plus_plus
    record = tune(cfg, settings, vlm, train_set, out)
    shown = f"{len(record['ids'])} soft vectors" if record.get("soft") else repr(record["text"])
    print(f"defense prefix: {shown} (loss {record['history'][0]:.4f} -> {record['history'][-1]:.4f}); "
          f"{out / 'prefix.json'} (evaluate with defense={cfg.defense.name} "
          f"defense.prefix_path={out / 'prefix.json'})")
    if not cfg.task.get("test_after_fit"):
        return None
    return _test(cfg, prefixed(vlm, record, f"{vlm.name}+{cfg.defense.name}"), out / "test")


def _tune_pat_plus_plus(cfg: DictConfig, settings: dict, vlm, train_set, out: Path) -> dict:
    """PAT++: hard examples found by asking the model, then the prefix tuned by GCG (or, soft, by Adam)."""
    from lanevil_train.tasks.vlm_evaluate import build_judge
    from lanevil_train.vlm.defenses.pat import GCGSettings, PrefixObjective, SoftSettings, tune_prefix, tune_soft_prefix

    judge = build_judge(cfg, out) if settings["hardness"] == "judge" else None
    choosing = {"model": vlm.identity(), "seed": int(cfg.seed),
                **{key: settings[key] for key in ("hardness", "hard_target", "examples", "pool_clips")}}
    chosen = choose_examples(vlm, train_set, settings, judge, out / EXAMPLES_FILE, choosing, cfg.progress)
    benign, hard = (examples_of(train_set, [e for e in chosen if e["hard"] == kind]) for kind in (False, True))
    objective = PrefixObjective(vlm, benign, hard, alpha=settings["alpha"], chunk=settings["chunk"])
    facts = {**choosing, "examples": [[e["index"], e["qa_id"], e["hard"], e["target"]] for e in chosen]}
    if settings["soft"]:
        soft = SoftSettings(steps=settings["steps"], prefix_length=settings["prefix_length"], lr=settings["soft_lr"],
                            seed=int(cfg.seed))
        return tune_soft_prefix(objective, soft, out, progress=cfg.progress, facts=facts)
    gcg = GCGSettings(steps=settings["steps"], prefix_length=settings["prefix_length"], top_k=settings["top_k"],
                      num_candidates=settings["num_candidates"], seed=int(cfg.seed))
    return tune_prefix(objective, gcg, out, progress=cfg.progress, facts=facts)


def _tune_pat(cfg: DictConfig, settings: dict, vlm, train_set, out: Path) -> dict:
    """PAT: attacked and benign examples drawn from the train split, then prefix and attack suffix in turn."""
    from lanevil_train.vlm.defenses.pat_baseline import PATSettings, tune_pat

    choosing = {"method": "pat", "seed": int(cfg.seed), "examples": settings["examples"],
                "pool_clips": settings["pool_clips"]}
    chosen = choose_pat_examples(train_set, settings, out / EXAMPLES_FILE, choosing)
    attacked = examples_of(train_set, [e for e in chosen if e["attacked"]])
    benign = examples_of(train_set, [e for e in chosen if not e["attacked"]])
    gcg = PATSettings(steps=settings["steps"], prefix_length=settings["prefix_length"], top_k=settings["top_k"],
                      num_candidates=settings["num_candidates"], seed=int(cfg.seed),
                      suffix_length=settings["suffix_length"])
    facts = {"model": vlm.identity(), **choosing,
             "examples": [[e["index"], e["qa_id"], e["attacked"], e["wrong"]] for e in chosen]}
    return tune_pat(vlm, attacked, [e["wrong"] for e in chosen if e["attacked"]], benign, gcg, settings["alpha"],
                    out, chunk=settings["chunk"], progress=cfg.progress, facts=facts)


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


def choose_pat_examples(train_set, settings: dict, path: Path, choosing: dict) -> list[dict]:
    """PAT's examples, drawn without asking the model: `examples` closed questions of perturbed clip variants to
    attack (each with the wrong answer the attack pushes toward) and `examples` questions of clean variants as
    benign ones, from `pool_clips` variants spread over the train split (seed choosing["seed"]); kept in `path`."""
    import numpy as np

    from lanevil_train.tasks.vlm_train import spread
    from lanevil_train.vlm.defenses.pat_baseline import wrong_answer

    stored = _stored_examples(path, choosing)
    if stored is not None:
        return stored
    rng = np.random.default_rng(choosing["seed"])
    perturbed = [i for i in range(len(train_set)) if train_set.clip_meta(i)["severity"] > 0]
    clean = [i for i in range(len(train_set)) if train_set.clip_meta(i)["severity"] == 0]
    attackable, benign = [], []
    for attacked, variants in ((True, perturbed), (False, clean)):
        for index in spread(variants, settings["pool_clips"])[:settings["pool_clips"]]:
            for qa in train_set.qa_for(train_set.clip_meta(index)["base_clip_id"]):
                if attacked and qa["type"] != "open":
                    attackable.append({"index": index, "qa_id": qa["qa_id"], "attacked": True,
                                       "target": qa["answer"], "wrong": wrong_answer(qa, int(rng.integers(3)))})
                elif not attacked:
                    benign.append({"index": index, "qa_id": qa["qa_id"], "attacked": False, "target": qa["answer"],
                                   "wrong": None})
    if not attackable or not benign:
        raise ValueError(f"defense.pool_clips: {settings['pool_clips']} clean and perturbed train clips hold "
                         f"{len(benign)} questions and {len(attackable)} closed questions; PAT needs both (raise "
                         f"defense.pool_clips, or train on a split with perturbed clips)")
    chosen = [group[i] for group in (benign, attackable)
              for i in sorted(rng.permutation(len(group))[:settings["examples"]].tolist())]
    atomic_write_text(path, json.dumps({"choosing": choosing, "examples": chosen}, indent=1))
    return chosen


def _test(cfg: DictConfig, defended, out: Path) -> float:
    """The defended VLM tested as task=evaluate would, its defense named in the report."""
    from lanevil_train.tasks.vlm_train import test_vlm

    score = test_vlm(cfg, defended, cfg.task.get("label") or defended.name, out)
    add_defense_to_report(out, defended)
    return score


def choose_examples(vlm, train_set, settings: dict, judge, path: Path, choosing: dict, progress: str) -> list[dict]:
    """Benign and hard examples of the train split: the answers to the pool's questions scored, those below the
    mean hard; `examples` of each drawn at random (choosing["seed"]). Kept in `path` with `choosing` (what they
    were chosen by), and read back from it when a rerun chooses by the same; a rerun that would choose otherwise
    is refused."""
    import numpy as np

    from lanevil_train.progress import progress_counter
    from lanevil_train.tasks.vlm_train import spread
    from lanevil_train.vlm.clips.qa_records import answer_is_correct, prompt_text
    from lanevil_train.vlm.defenses.pat import hard_mask

    stored = _stored_examples(path, choosing)
    if stored is not None:
        return stored
    closed = settings["hardness"] == "accuracy"
    indices = spread(list(range(len(train_set))), settings["pool_clips"])[:settings["pool_clips"]]
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
                         f"by defense.hardness={settings['hardness']}")
    if closed:
        scores = [float(bool(answer_is_correct(qa, text))) for (_, qa), text in zip(pool, answers)]
    elif settings["hardness"] == "language":  # each answer's own Language score against its reference
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
        print(f"PAT++: all {len(scores)} answers of the pool score {scores[0]:g} by {settings['hardness']}: no hard "
              f"examples, so the prefix is tuned on benign ones only")
    rng = np.random.default_rng(choosing["seed"])
    chosen = []
    for kind in (False, True):
        members = [i for i, h in enumerate(hard) if h == kind]
        for i in sorted(rng.permutation(members)[:settings["examples"]].tolist()):
            index, qa = pool[i]
            chosen.append({"index": index, "qa_id": qa["qa_id"], "hard": kind, "score": scores[i],
                           "answer": answers[i], "target": _target(qa, kind, settings["hard_target"])})
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
