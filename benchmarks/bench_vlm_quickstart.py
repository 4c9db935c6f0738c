"""Benchmark: building the embedded VLM of experiment=vlm_quickstart (the scene truth of the tokenizer's clips, the
vision pretraining's clips rendered, the tokenizer, the tower pretrained) with its clips prepared in this process
(model.embedded.workers=0) and in worker processes (auto), and whether both give the very same model.

Run: ``python benchmarks/bench_vlm_quickstart.py [--workers 0 auto] [--pretraining-steps 600]``. Each setting builds
into its own folder (the run's init/) in a fresh process, from the quickstart's own config; the seconds of each
phase come from the timing of its calls, and the weights are compared file for file (safetensors bytes).
The whole quickstart is timed by running it: ``/usr/bin/time -v python -m lanevil_train experiment=vlm_quickstart``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def build(workers: str, steps: int, out: Path) -> dict:
    """Build the quickstart's embedded VLM into `out` with model.embedded.workers=`workers`; seconds per phase and
    the weights' digest."""
    from hydra import compose, initialize_config_module

    import lanevil_train.tasks.vlm.train as vlm_train
    from lanevil_train.tasks.builders import build_split
    from lanevil_train.vlm.backends import embedded

    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "experiment=vlm_quickstart", f"model.embedded.workers={workers}", "progress=none",
            f"model.embedded.vision_pretraining.steps={steps}"])
    seconds: dict[str, float] = {}

    def timed(name, fn):
        def run(*args, **kwargs):
            start = time.perf_counter()
            result = fn(*args, **kwargs)
            seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - start
            return result
        return run

    vlm_train.prepare_clips = timed("truth and frames", vlm_train.prepare_clips)
    embedded.make_embedded_vlm = timed("tokenizer and model", embedded.make_embedded_vlm)
    embedded.pretrain_vision = timed("vision pretraining", embedded.pretrain_vision)
    start = time.perf_counter()
    train_set = build_split(cfg, "train")
    seconds["train split"] = time.perf_counter() - start
    start = time.perf_counter()
    init = vlm_train.base_model_dir(cfg, train_set, out)
    seconds["whole build"] = time.perf_counter() - start
    digest = hashlib.sha256((init / "model.safetensors").read_bytes()).hexdigest()[:16]
    return {"workers": workers, "resolved_workers": vlm_train.render_workers(workers),
            **{k: round(v, 1) for k, v in seconds.items()}, "weights_sha256": digest}


def main() -> None:
    """Print one JSON line per setting, then whether their weights are the same."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--workers", nargs="+", default=["0", "auto"])
    ap.add_argument("--pretraining-steps", type=int, default=600)
    ap.add_argument("--one", nargs=2, metavar=("WORKERS", "OUT"), help=argparse.SUPPRESS)  # a child run
    args = ap.parse_args()
    if args.one:
        print(json.dumps(build(args.one[0], args.pretraining_steps, Path(args.one[1]))))
        return
    results = []
    for workers in args.workers:
        with tempfile.TemporaryDirectory() as out:
            child = subprocess.run([sys.executable, __file__, "--one", workers, out, "--pretraining-steps",
                                    str(args.pretraining_steps)], capture_output=True, text=True, check=True)
        results.append(json.loads(child.stdout.strip().splitlines()[-1]))
        print(json.dumps(results[-1]))
    print(json.dumps({"same_weights": len({r["weights_sha256"] for r in results}) == 1}))


if __name__ == "__main__":
    main()
