"""Time and memory of each VLM defense on a trained VLM: a fine-tuning step with each visual defense (none, mixup,
pgd, aam, aam++), and a tuning step of each textual one (PAT++ by GCG, its soft variant by Adam, PAT's attack and
defense steps), each method in a process of its own so its peak resident memory is its own.

    python benchmarks/bench_vlm_defenses.py --model outputs/train/<date>/model          # every method
    python benchmarks/bench_vlm_defenses.py --model RUN/model --method pat++ --steps 3   # one

The batches are the compare's (benchmarks/RESULTS.md "VLM defenses"): 16 (clip, question) pairs of 64x112 clips of
the train split, full fine-tuning with the vision tower frozen; PAT++ and PAT with 8 + 8 examples, top-k 256, 128
candidates per step in chunks of 64, a 20-token prefix (and suffix). The clips are rendered before the clock starts.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

VISUAL = ("none", "mixup", "pgd", "aam", "aam++")
TEXTUAL = ("pat++", "pat++ soft", "pat")


def _batches(size: tuple[int, int], count: int, batch: int = 16) -> list[list[dict]]:
    """`count` batches of (clip, QA) items of the train split (clean and severity 3), rendered now."""
    from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite
    from lanevil_train.vlm.clips.qa_data import ClipQADataset

    suite = SyntheticClipSuite(8, 0, severities=(3,), size=size, per_clip=5)
    data = ClipQADataset(suite, "all")
    step = max(1, len(data) // (count * batch))
    items = [data[i] for i in range(0, len(data), step)][:count * batch]
    return [items[k * batch:(k + 1) * batch] for k in range(count)]


def time_visual(model: str, method: str, steps: int) -> dict:
    """Seconds per fine-tuning step (the first, warm-up step left out) with the callback or mixer that
    `defense=<method>` builds for a VLM (tasks/vlm/train.visual_defense, from the method's config)."""
    import pytorch_lightning as pl
    import torch
    from hydra import compose, initialize_config_module
    from torch.utils.data import DataLoader

    from lanevil_train.tasks.vlm.train import visual_defense
    from lanevil_train.vlm.clips.qa_data import MixingClipCollate, collate_clip_qa
    from lanevil_train.vlm.training.finetune import VLMFineTuner

    torch.manual_seed(0)
    module = VLMFineTuner(model, lora=None, lr=3e-4, frames_as="video")
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=["model=vlm/hf", f"model.path={model}", f"defense={method}"])
    callback, mixer = visual_defense(cfg, module)
    callbacks = [callback] if callback is not None else []
    collate = MixingClipCollate(mixer) if mixer is not None else collate_clip_qa
    items = [item for batch in _batches((64, 112), steps + 1) for item in batch]
    loader = DataLoader(items, batch_size=16, shuffle=False, collate_fn=collate)
    stamps = []

    class Clock(pl.Callback):
        def on_train_batch_end(self, *args):
            stamps.append(time.perf_counter())

    trainer = pl.Trainer(max_steps=steps + 1, callbacks=[*callbacks, Clock()], accelerator="cpu", devices=1,
                         logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, num_sanity_val_steps=0)
    trainer.fit(module, loader)
    return {"seconds_per_step": (stamps[-1] - stamps[0]) / (len(stamps) - 1), "steps": len(stamps) - 1}


def time_textual(model: str, method: str, steps: int) -> dict:
    """Seconds per tuning step of the method (GCG for PAT++ and PAT, Adam for the soft prefix): one step first,
    then `steps` more timed, resumed from it (so the start's scoring is not counted)."""
    import tempfile

    import numpy as np

    from lanevil_train.vlm.backends.hf import HFVLM
    from lanevil_train.vlm.defenses.gcg import Examples
    from lanevil_train.vlm.defenses.pat import (
        RES_GOAL,
        GCGSettings,
        PrefixObjective,
        SoftSettings,
        tune_prefix,
        tune_soft_prefix,
    )
    from lanevil_train.vlm.defenses.pat_baseline import PATSettings, tune_pat

    vlm = HFVLM(model, dtype="float32", device="cpu", frames_as="video")
    vlm.model.requires_grad_(False)
    items = _batches((64, 112), 1)[0]
    clips = [[np.asarray(f) for f in item["frames"]] for item in items]
    questions = [item["question"] for item in items]
    benign = Examples(clips[:8], questions[:8], [item["answer"] for item in items[:8]])
    hard = Examples(clips[8:], questions[8:], [RES_GOAL] * 8)
    attacked = Examples(clips[8:], questions[8:], [item["answer"] for item in items[8:]])
    wrong = ["Yes." if item["answer"].lower().startswith("no") else "No." for item in items[8:]]
    out = tempfile.mkdtemp()

    def tune(total: int) -> None:
        if method == "pat":
            tune_pat(vlm, attacked, wrong, benign, PATSettings(steps=total), alpha=0.2, out_dir=out, progress="none")
        elif method == "pat++ soft":
            tune_soft_prefix(PrefixObjective(vlm, benign, hard), SoftSettings(steps=total), out, progress="none")
        else:
            tune_prefix(PrefixObjective(vlm, benign, hard), GCGSettings(steps=total), out, progress="none")

    tune(1)
    start = time.perf_counter()
    tune(1 + steps)
    return {"seconds_per_step": (time.perf_counter() - start) / steps, "steps": steps}


def run_one(model: str, method: str, steps: int) -> dict:
    result = (time_visual if method in VISUAL else time_textual)(model, method, steps)
    return {"method": method, **result, "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="a trained VLM's folder, e.g. the vlm_quickstart's model/")
    parser.add_argument("--method", choices=(*VISUAL, *TEXTUAL), help="one method (default: each, in turn)")
    parser.add_argument("--steps", type=int, default=None, help="steps timed (default: 10 fine-tuning, 2 tuning)")
    args = parser.parse_args()
    if args.method is not None:
        steps = args.steps or (10 if args.method in VISUAL else 2)
        print(json.dumps(run_one(args.model, args.method, steps)))
        return
    print("| defense | step | seconds per step | peak RSS (GB) |\n|---|---|---|---|")
    for method in (*VISUAL, *TEXTUAL):
        command = [sys.executable, __file__, "--model", args.model, "--method", method]
        command += ["--steps", str(args.steps)] if args.steps else []
        line = subprocess.run(command, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
        result = json.loads(line)
        kind = "fine-tuning (batch 16)" if method in VISUAL else "tuning (GCG)" if method != "pat++ soft" else \
            "tuning (Adam)"
        print(f"| {method} | {kind} | {result['seconds_per_step']:.2f} | {result['peak_rss_gb']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
