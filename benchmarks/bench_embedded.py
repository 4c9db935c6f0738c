"""The embedded VLM's learning experiment: train it on the simulated train split, score it on held-out clips.

    python benchmarks/bench_embedded.py --out /tmp/bench_embedded [--steps 150 --batch 16 --lr 3e-3]

1. Renders the train split (seeds 0.., each base clip clean and at one severity, 1..5 by seed) and the test split
   (seeds from 1,000,000; never overlapping) at the model's frame size, once: cached under --cache as .npz chunks
   (atomic; a rerun reuses them).
2. Builds the embedded VLM (tokenizer trained on the train split's QA), trains it with the recipe
   (`fit_answers`: AdamW, warmup + cosine) on (clip variant, QA) pairs drawn at random, clean and perturbed.
3. Trains the "blind" ablation the same way (same seed, steps, batches) on grey frames: what text alone gives.
4. Answers every held-out QA (clean and perturbed variants) with both, through HFVLM.answer, and reports accuracy
   on yes/no and choice questions against the majority-answer baseline (the train split's most common first word
   / letter), and how often open answers name the true lane count, ego lane, weather and steering (vs the most
   common fact of the train split, and vs the blind model). Writes results.json and a few answers to --out.
With --pretrain-vision N, step 2 starts with N steps of vision-tower pretraining on the scene truth
(embedded.pretrain_vision, on every train clip variant and, as the recipe does, their mirror images) and then keeps
the tower frozen. With --aids N each train clip variant is also paired N times with each of its training aids
(qa.training_aids), as model.fine_tune.aids does.
"""

from __future__ import annotations

import argparse
import io
import json
import re
import sys
import time
from collections import Counter
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from lanevil_train.files.atomic import atomic_write_bytes, atomic_write_text
from lanevil_train.taxonomy import ILLUSION_NAMES
from lanevil_train.vlm.backends.embedded import (
    GREY,
    build_embedded_vlm,
    count_parameters,
    fit_answers,
    pretrain_vision,
    qa_corpus,
)
from lanevil_train.vlm.backends.hf import HFVLM
from lanevil_train.vlm.clips import clips as geometry
from lanevil_train.vlm.clips.clip_set import SEGMENTS, base_clip_id
from lanevil_train.vlm.clips.qa import scene_classes, training_aids
from lanevil_train.vlm.clips.qa_facts import WEATHER_TEXT
from lanevil_train.vlm.clips.qa_records import answer_is_correct, chosen_letter, prompt_text
from lanevil_train.vlm.clips.suite_qa import suite_qa

TEST_FIRST_SEED = 1_000_000
CHUNK = 25  # cases per cache file


# ---------------------------------------------------------------------------------------------- clips

def _render_case(args) -> list[dict]:
    """The 3 base clips of one case: frames [2, 6, H, W, 3] (clean, perturbed at the case's severity)."""
    case, size = args
    severity = 1 + case.seed % 5
    out = []
    for segment in SEGMENTS:
        base = base_clip_id(case, segment)
        rendered = geometry.render_clip(case, segment, [0, severity], size=size)
        out.append({"frames": np.stack([np.stack(rendered[0]), np.stack(rendered[severity])]),
                    "severity": severity, "base_clip_id": base})
    return out


def load_split(first_seed: int, num_cases: int, size: tuple[int, int], cache: Path, workers: int) -> list[dict]:
    """The base clips of cases first_seed.. (+num_cases), rendered once and cached in CHUNK-case .npz files."""
    cases = geometry.clip_cases(num_cases, first_seed, list(ILLUSION_NAMES))
    clips: list[dict] = []
    for start in range(0, num_cases, CHUNK):
        path = cache / f"clips_{size[0]}x{size[1]}_{first_seed + start}_{min(CHUNK, num_cases - start)}.npz"
        if not path.is_file():
            with Pool(workers) as pool:
                rendered = [c for group in pool.map(_render_case, [(case, size) for case in
                                                                    cases[start:start + CHUNK]]) for c in group]
            buffer = io.BytesIO()
            np.savez(buffer, frames=np.stack([c["frames"] for c in rendered]),
                     meta=json.dumps([{k: v for k, v in c.items() if k != "frames"} for c in rendered]))
            atomic_write_bytes(path, buffer.getvalue())
        with np.load(path) as data:
            for frames, meta in zip(data["frames"], json.loads(str(data["meta"]))):
                clips.append({**meta, "frames": frames})
    return clips


def add_truth_facts(clips: list[dict], first_seed: int, size: tuple[int, int], cache: Path) -> None:
    """Give each base clip its QA (planned over the split, suite_qa.suite_qa), its training-only QA (qa.training_aids:
    the scene description and the open questions naming its facts) and scene classes (qa.scene_classes, what the
    vision tower is pretrained on), cached as JSON."""
    path = cache / f"facts_qa2_{size[0]}x{size[1]}_{first_seed}_{len(clips) // len(SEGMENTS)}.json"
    if not path.is_file():
        cases = geometry.clip_cases(len(clips) // len(SEGMENTS), first_seed, list(ILLUSION_NAMES))
        truths = [(base_clip_id(case, segment), case.seed, geometry.clip_truth(case, segment, size=size))
                  for case in cases for segment in SEGMENTS]
        planned = suite_qa(truths)
        facts = {base: {"qa": planned[base], "aids": training_aids(truth, base), "classes": scene_classes(truth, base)}
                 for base, _, truth in truths}
        atomic_write_text(path, json.dumps(facts))
    facts = json.loads(path.read_text())
    for clip in clips:
        clip.update(facts[clip["base_clip_id"]])


def pairs_of(clips: list[dict], variants=(0, 1), aids: int = 0) -> list[tuple[int, int, dict]]:
    """(clip index, variant, QA) for every QA of every clip variant, and `aids` times each of its training aids."""
    return [(i, v, qa) for i, clip in enumerate(clips) for v in variants
            for qa in clip["qa"] + (clip["aids"] * aids if aids else [])]


def clip_frames(clips: list[dict], index: int, variant: int, blind: bool) -> list[np.ndarray]:
    """The 6 frames of one clip variant (grey frames of the same size when blind)."""
    frames = clips[index]["frames"][variant]
    return [np.full_like(f, GREY) if blind else f for f in frames]


# ---------------------------------------------------------------------------------------------- scores

def first_answer(qa: dict, text: str) -> str | None:
    """What a yes/no or choice answer decides: its first word ("yes"/"no") or its option letter."""
    if qa["type"] == "choice":
        return chosen_letter(qa, text)
    words = re.sub(r"[^a-z ]+", " ", text.lower()).split()
    return words[0] if words else None


def majority_answers(train_qas: list[dict]) -> dict[str, str]:
    """The most common yes/no word and choice letter of the train split."""
    counts = {kind: Counter(first_answer(qa, qa["answer"]) for qa in train_qas if qa["type"] == kind)
              for kind in ("yes_no", "choice")}
    return {kind: count.most_common(1)[0][0] for kind, count in counts.items()}


def majority_text(qa: dict, majority: dict[str, str]) -> str:
    """The majority baseline's answer to a yes/no or choice QA."""
    return "Yes." if majority[qa["type"]] == "yes" else ("No." if qa["type"] == "yes_no" else majority["choice"])


def first_cue(text: str, cues) -> str | None:
    """The value of whichever (value, cue) pair's cue comes first in the text (None when none is there): an answer
    that runs on into other phrases is read by what it says first."""
    found = [(at, value) for value, cue in cues if (at := text.lower().find(cue)) >= 0]
    return min(found)[1] if found else None


_WEATHER_CUES = [(key, text.split(",")[0].split(" with ")[0].lower()) for key, text in WEATHER_TEXT.items()]
_STEERING_CUES = [("left", "steer gently to the left"), ("right", "steer gently to the right"),
                  ("straight", "no steering"), ("straight", "hold a straight course"),
                  ("curve", "follow the road's curve")]
FACTS = {
    "lane_count": lambda text: (m.group(1) if (m := re.search(r"\b(two|three|four|five) lanes\b", text.lower()))
                                else None),
    "ego_lane": lambda text: (m.group(1) if (m := re.search(r"(?:is in|stay in) (the leftmost lane|the rightmost lane|"
                                                            r"the \w+ lane from the left)", text.lower())) else None),
    "weather": lambda text: first_cue(text, _WEATHER_CUES),
    "steering": lambda text: first_cue(text, _STEERING_CUES),
}


def fact_hits(qas: list[dict], answers: list[str]) -> dict[str, dict]:
    """Per fact: among open QA whose reference names it, how often the answer names the same value."""
    out = {}
    for fact, read in FACTS.items():
        named = [(read(qa["answer"]), read(ans)) for qa, ans in zip(qas, answers)
                 if qa["type"] == "open" and read(qa["answer"]) is not None]
        out[fact] = {"n": len(named), "hit": sum(ref == got for ref, got in named) / max(1, len(named))}
    return out


def fact_chance(train_qas: list[dict], test_qas: list[dict]) -> dict[str, float]:
    """Per fact: the hit rate of always naming the train split's most common value."""
    out = {}
    for fact, read in FACTS.items():
        common = Counter(read(qa["answer"]) for qa in train_qas if qa["type"] == "open"
                         and read(qa["answer"]) is not None).most_common(1)
        refs = [read(qa["answer"]) for qa in test_qas if qa["type"] == "open" and read(qa["answer"]) is not None]
        out[fact] = sum(r == common[0][0] for r in refs) / max(1, len(refs)) if common else 0.0
    return out


def accuracy(qas: list[dict], answers: list[str]) -> dict[str, float]:
    """Accuracy on yes/no and on choice questions."""
    out = {}
    for kind in ("yes_no", "choice"):
        marks = [answer_is_correct(qa, ans) for qa, ans in zip(qas, answers) if qa["type"] == kind]
        out[kind] = sum(marks) / max(1, len(marks))
    return out


# ---------------------------------------------------------------------------------------------- run

def train(model_dir: Path, clips: list[dict], args, blind: bool) -> tuple[HFVLM, dict]:
    """Load the built model, train it by the recipe on the train pairs (grey frames when blind); the model and
    what training did."""
    vlm = HFVLM(model_dir, max_new_tokens=args.max_new_tokens, batch_size=args.eval_batch, device="cpu")
    pairs = pairs_of(clips, aids=args.aids)
    rng = np.random.default_rng(args.seed)

    def sample_batch(step: int):
        chosen = [pairs[i] for i in rng.integers(len(pairs), size=args.batch)]
        return ([clip_frames(clips, i, v, blind) for i, v, _ in chosen], [prompt_text(qa) for _, _, qa in chosen],
                [qa["answer"] for _, _, qa in chosen])

    import torch
    torch.manual_seed(args.seed)
    start = time.perf_counter()
    if args.pretrain_vision:
        variants = [(i, v) for i in range(len(clips)) for v in (0, 1)]

        def scene_batch(step: int):
            chosen = [variants[i] for i in rng.integers(len(variants), size=args.batch)]
            return [clip_frames(clips, i, v, blind) for i, v in chosen], [clips[i]["classes"] for i, _ in chosen]

        pretrain_vision(vlm.model, vlm.processor, scene_batch, args.pretrain_vision, lr=args.pretrain_lr,
                        mirror=not args.no_pretrain_mirror, seed=args.seed, progress="none",
                        log=lambda m: print(("blind " if blind else "") + m, flush=True))
        vlm.model.model.visual.requires_grad_(False)  # the recipe's fine_tune.freeze_vision
    losses = fit_answers(vlm, sample_batch, args.steps, lr=args.lr, warmup=args.warmup,
                         log=lambda m: print(("blind " if blind else "") + m, flush=True))
    minutes = (time.perf_counter() - start) / 60
    tail = max(1, args.steps // 10)
    return vlm, {"minutes": minutes, "first_loss": float(np.mean(losses[:tail])),
                 "last_loss": float(np.mean(losses[-tail:]))}


def held_out_loss(vlm: HFVLM, clips: list[dict], pairs: list, blind: bool, batch: int = 16) -> float:
    """Mean answer loss over held-out pairs."""
    import torch
    total = []
    with torch.no_grad():
        for s in range(0, len(pairs), batch):
            chunk = pairs[s:s + batch]
            total += vlm.answer_loss([clip_frames(clips, i, v, blind) for i, v, _ in chunk],
                                     [prompt_text(qa) for _, _, qa in chunk],
                                     [qa["answer"] for _, _, qa in chunk]).tolist()
    return float(np.mean(total))


def answer_all(vlm: HFVLM, clips: list[dict], pairs: list, blind: bool) -> tuple[list[str], float]:
    """Answers to every pair (grey frames when blind) and answers per second."""
    start = time.perf_counter()
    answers = vlm.answer([clip_frames(clips, i, v, blind) for i, v, _ in pairs], [prompt_text(qa) for *_, qa in pairs])
    return answers, len(pairs) / (time.perf_counter() - start)


def score(qas, answers) -> dict:
    return {"accuracy": accuracy(qas, answers), "open_facts": fact_hits(qas, answers)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/lanevil_embedded_clips"))
    parser.add_argument("--train-cases", type=int, default=600)
    parser.add_argument("--test-cases", type=int, default=30)
    parser.add_argument("--frame-size", type=int, nargs=2, default=(64, 112))
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--warmup", type=int, default=15)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--max-new-tokens", type=int, default=48)
    parser.add_argument("--eval-batch", type=int, default=16)
    parser.add_argument("--aids", type=int, default=0,
                        help="rounds of training aids per train clip variant beside its QA (qa.training_aids: the "
                             "scene description and 4 fact questions; the recipe's aid to reading the frames; 0: QA "
                             "only)")
    parser.add_argument("--pretrain-vision", type=int, default=0,
                        help="steps of vision-tower pretraining on the scene truth (embedded.pretrain_vision) before "
                             "the answer loss, which then leaves the tower frozen (0: none, the tower trains too)")
    parser.add_argument("--pretrain-lr", type=float, default=1e-3)
    parser.add_argument("--no-pretrain-mirror", action="store_true",
                        help="pretrain the tower without its left-right mirror images (the recipe flips half a batch)")
    parser.add_argument("--no-blind", action="store_true", help="skip the blind (grey-frame) ablation")
    parser.add_argument("--blind-only", action="store_true", help="run only the blind (grey-frame) ablation")
    args = parser.parse_args(argv)
    if args.train_cases >= TEST_FIRST_SEED:
        sys.exit(f"--train-cases {args.train_cases}: the train seeds would reach the test split's {TEST_FIRST_SEED}")
    size = tuple(args.frame_size)
    args.cache.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    train_clips = load_split(0, args.train_cases, size, args.cache, args.workers)
    test_clips = load_split(TEST_FIRST_SEED, args.test_cases, size, args.cache, args.workers)
    print(f"clips ready in {time.perf_counter() - start:.0f} s: {len(train_clips)} train, {len(test_clips)} test "
          f"base clips", flush=True)
    if args.aids or args.pretrain_vision:
        add_truth_facts(train_clips, 0, size, args.cache)
    train_qas = [qa for clip in train_clips for qa in clip["qa"]]
    results: dict = {"args": {k: (list(v) if isinstance(v, tuple) else str(v) if isinstance(v, Path) else v)
                              for k, v in vars(args).items()}}
    test_pairs = {"clean": pairs_of(test_clips, (0,)), "perturbed": pairs_of(test_clips, (1,))}
    test_qas = [qa for *_, qa in test_pairs["clean"]]
    majority = majority_answers(train_qas)
    results["majority"] = {"answers": majority, "accuracy": accuracy(test_qas, [majority_text(qa, majority)
                                                                               if qa["type"] != "open" else ""
                                                                               for qa in test_qas]),
                           "open_fact_chance": fact_chance(train_qas, test_qas)}
    for blind in ([False] if args.no_blind else [True] if args.blind_only else [False, True]):
        name = "blind" if blind else "embedded"
        model_dir = args.out / f"model_{name}"
        if not model_dir.is_dir():
            aids = [aid for clip in train_clips for aid in clip["aids"]] if args.aids else []
            build_embedded_vlm(model_dir, qa_corpus(train_qas + aids), frame_size=size, seed=args.seed)
        vlm, trained = train(model_dir, train_clips, args, blind)
        trained["parameters"] = count_parameters(vlm.model)
        trained["held_out_loss"] = held_out_loss(vlm, test_clips, test_pairs["clean"][:256], blind)
        entry = {"training": trained}
        for variant, pairs in test_pairs.items():
            answers, rate = answer_all(vlm, test_clips, pairs, blind)
            entry[variant] = {**score([qa for *_, qa in pairs], answers), "answers_per_s": rate}
            if variant == "clean":
                atomic_write_text(args.out / f"answers_{name}.jsonl", "".join(
                    json.dumps({"q": prompt_text(qa), "ref": qa["answer"], "got": a}) + "\n"
                    for (_, _, qa), a in zip(pairs, answers)))
        results[name] = entry
        print(json.dumps({name: entry}, indent=1), flush=True)
    results["minutes_total"] = (time.perf_counter() - start) / 60
    atomic_write_text(args.out / "results.json", json.dumps(results, indent=1))
    print(json.dumps({k: results[k] for k in ("majority", "minutes_total")}, indent=1))


if __name__ == "__main__":
    main()
