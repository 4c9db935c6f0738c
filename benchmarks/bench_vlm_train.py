"""VLM fine-tuning step time and peak memory: LoRA vs full, on a tiny offline model (lanevil_dev/tiny_vlm.py).

Each (family, mode) runs in its own process so its peak RSS is its own. A step is VLMFineTuner.batch_loss on a
batch of `batch` (clip, question, answer) pairs of 6 random frames, backward, AdamW step; the first `warmup` steps
are not timed. Peak memory: the process's max RSS, and torch.cuda.max_memory_allocated on a CUDA device.

    python benchmarks/bench_vlm_train.py                     # qwen2_vl and llava, lora and full, on the CPU
    python benchmarks/bench_vlm_train.py --families qwen2_vl --steps 20 --size 64 112
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# lanevil_dev (the test doubles of a source checkout, not in the wheel) is imported from the checkout root
CHECKOUT = Path(__file__).resolve().parents[1]
if str(CHECKOUT) not in sys.path:
    sys.path.insert(0, str(CHECKOUT))


def run_one(family: str, mode: str, steps: int, warmup: int, batch: int, size: tuple[int, int], device: str) -> dict:
    """Time `steps` optimizer steps of one setup; its s/step, peak RSS (MiB) and CUDA peak (MiB) as a dict."""
    import numpy as np
    import torch

    from lanevil_dev.tiny_vlm import build_tiny_vlm
    from lanevil_train.vlm.training.finetune import VLMFineTuner, collate_clip_qa

    torch.manual_seed(0)
    model_dir = build_tiny_vlm(family, Path(tempfile.mkdtemp()) / family)
    lora = {"r": 8, "alpha": 16, "dropout": 0.0} if mode == "lora" else None
    module = VLMFineTuner(str(model_dir), lora=lora, dtype="auto").to(device)
    rng = np.random.default_rng(0)
    items = [{"frames": rng.integers(0, 256, (6, *size, 3), dtype=np.uint8), "question": "How many lanes are there?",
              "answer": "The road has three lanes.", "key": str(i), "meta": {}} for i in range(batch)]
    data = collate_clip_qa(items)
    params = [p for p in module.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=1e-4)
    module.train()
    for step in range(warmup + steps):
        if step == warmup:
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            start = time.perf_counter()
        loss = module.batch_loss(data).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    elapsed = time.perf_counter() - start
    return {"family": family, "mode": mode, "device": device, "batch": batch, "frames": list(size),
            "trainable": sum(p.numel() for p in params), "total": sum(p.numel() for p in module.parameters()),
            "s_per_step": elapsed / steps, "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "cuda_peak_mib": (torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda") else None)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=["qwen2_vl", "llava"])
    parser.add_argument("--modes", nargs="+", default=["lora", "full"], choices=["lora", "full"])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--size", type=int, nargs=2, default=[32, 48], metavar=("H", "W"))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # the child process of one setup
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.families[0], args.modes[0], args.steps, args.warmup, args.batch,
                                 tuple(args.size), args.device)))
        return
    import torch

    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}")
    for family in args.families:
        for mode in args.modes:
            command = [sys.executable, __file__, "--one", "--families", family, "--modes", mode, "--steps",
                       str(args.steps), "--warmup", str(args.warmup), "--batch", str(args.batch), "--size",
                       *map(str, args.size), "--device", args.device]
            result = subprocess.run(command, capture_output=True, text=True, check=True)
            row = json.loads(result.stdout.strip().splitlines()[-1])
            cuda = f", CUDA peak {row['cuda_peak_mib']:.0f} MiB" if row["cuda_peak_mib"] is not None else ""
            print(f"{family:10s} {mode:4s} trainable {row['trainable']:>7d} of {row['total']:>7d} | "
                  f"{row['s_per_step']:.3f} s/step (batch {row['batch']}, {row['frames'][0]}x{row['frames'][1]}) | "
                  f"peak RSS {row['peak_rss_mib']:.0f} MiB{cuda}")


if __name__ == "__main__":
    main()
