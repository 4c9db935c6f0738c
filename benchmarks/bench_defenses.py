"""Training step time of every defense against the undefended step (same model, same batches).

Usage: python benchmarks/bench_defenses.py [--steps N] [--threads T] [--defenses none,aam++,...] [--ckpt last.ckpt]

The model and data are `experiment=quickstart` (LaneATT-ResNet18, 112x320, batch 8). A step is timed from
the first callback's on_train_batch_start to the last callback's on_train_batch_end, so it includes the
defense callback's hooks, forward, backward and the optimizer. Batches are prepared once and copied per
step; the data-only defenses (cutout, hsv, mixup, copypaste) are timed in the collate that applies them
(mixers) or in the sample pipeline (transforms), per batch of 8, and reported beside the step.
With --ckpt the weights come from a trained checkpoint (AAM's hard examples then have real attention).
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import pytorch_lightning as pl
import torch
from hydra import compose, initialize_config_module
from torch.utils.data import DataLoader, Dataset

from lanevil_train.checkpoints import load_weights
from lanevil_train.data.datamodule import ProcessedDataset
from lanevil_train.tasks.builders import build_datamodule, build_defense, build_model, model_config

DEFENSES = ("none", "cutout", "hsv", "mixup", "copypaste", "pgd", "aam", "aam++")


class CopiedBatches(Dataset):
    """The same prepared batches, deep-copied on every read (defenses edit batches in place)."""

    def __init__(self, batches: list[dict], length: int):
        self.batches, self.length = batches, length

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict:
        return copy.deepcopy(self.batches[index % len(self.batches)])


class StepClock(pl.Callback):
    def __init__(self):
        self.starts: list[float] = []
        self.times: list[float] = []

    def on_train_batch_start(self, *args) -> None:
        self.starts.append(time.perf_counter())


class StepEnd(pl.Callback):
    def __init__(self, clock: StepClock):
        self.clock = clock

    def on_train_batch_end(self, *args) -> None:
        self.clock.times.append(time.perf_counter() - self.clock.starts[-1])


def _as_is(batch: dict) -> dict:
    return batch  # keep the lanes numpy arrays, as the real collate does


def config(defense: str):
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        return compose(config_name="config", overrides=["experiment=quickstart", f"defense={defense}",
                                                        "data.train.num_scenes=64", "output_dir=/tmp/bench_defenses"])


def prepared_batches(cfg, model, defense: dict, count: int) -> tuple[list[dict], float]:
    """`count` training batches through the defense's data side, and the median seconds to make one."""
    datamodule = build_datamodule(cfg, ("train",), model, defense)
    loader = datamodule.train_dataloader()
    dataset = loader.dataset
    assert isinstance(dataset, ProcessedDataset)
    for index in range(len(dataset)):  # render (and cache) the scenes first: their cost is not the defense's
        dataset.base[index]
    batches, times = [], []
    iterator = iter(loader)
    for _ in range(count):
        t0 = time.perf_counter()
        batches.append(next(iterator))
        times.append(time.perf_counter() - t0)
    return batches, statistics.median(times)


def measure(defense_name: str, steps: int, ckpt: str | None) -> dict:
    cfg = config(defense_name)
    pl.seed_everything(0)
    model = build_model(model_config(cfg))
    if ckpt:
        load_weights(model, ckpt, "--ckpt")  # weights-only, checked to be this network's
    defense = build_defense(cfg)
    batches, batch_time = prepared_batches(cfg, model, defense, 8)
    clock = StepClock()
    callbacks = [clock] + ([defense["callback"]] if defense["callback"] else []) + [StepEnd(clock)]
    trainer = pl.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, callbacks=callbacks,
                         limit_val_batches=0)
    loader = DataLoader(CopiedBatches(batches, steps), batch_size=None, shuffle=False, collate_fn=_as_is)
    trainer.fit(model, loader)
    warm = clock.times[3:]  # the first steps allocate
    return {"defense": defense_name, "step_s": statistics.median(warm), "batch_s": batch_time,
            "bank": len(defense["callback"].bank) if hasattr(defense["callback"], "bank") else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=25)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--defenses", default=",".join(DEFENSES))
    parser.add_argument("--ckpt", default=None, help="a trained quickstart checkpoint (weights only)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = [measure(name, args.steps, args.ckpt) for name in args.defenses.split(",")]
    base = next((r["step_s"] for r in rows if r["defense"] == "none"), None)
    print(f"{'defense':<10} {'step (s)':>9} {'x none':>7} {'batch prep (s)':>15} {'bank':>6}")
    for r in rows:
        ratio = f"{r['step_s'] / base:.3f}" if base else "-"
        bank = "" if r["bank"] is None else r["bank"]
        print(f"{r['defense']:<10} {r['step_s']:>9.3f} {ratio:>7} {r['batch_s']:>15.4f} {bank:>6}")


if __name__ == "__main__":
    main()
