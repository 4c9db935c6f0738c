"""Two-process DDP on CPU (gloo): training runs, and the test metric reduces across ranks."""

from __future__ import annotations

import json
import os
import socket

import numpy as np
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from lanevil_train.evaluation.lane_records import read_records
from lanevil_train.metrics import TuSimpleMetric
from tests.tasks.cli_helpers import TINY, run_cli


def _random_image(rng: np.random.Generator) -> tuple[list, list, np.ndarray]:
    ys = np.arange(160, 720, 10, dtype=float)
    gt = [np.stack([200 + 250 * i + 0.3 * (720 - ys), ys], 1)[::-1] for i in range(rng.integers(2, 5))]
    preds = [lane + np.array([rng.normal(0, 12), 0]) for lane in gt if rng.random() < 0.8]
    return preds, gt, ys


def _cases(n: int = 16):
    rng = np.random.default_rng(7)
    return [_random_image(rng) for _ in range(n)]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _worker(rank: int, world: int, port: int, out_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    metric = TuSimpleMetric()
    for preds, gt, ys in _cases()[rank::world]:  # each rank sees a different half
        metric.update([preds], [gt], [ys])
    scores = {k: float(v) for k, v in metric.compute().items()}  # synced across ranks
    with open(os.path.join(out_dir, f"rank{rank}.json"), "w") as handle:
        json.dump(scores, handle)
    dist.destroy_process_group()


def test_metric_reduces_across_two_gloo_ranks(tmp_path):
    mp.spawn(_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=True)
    single = TuSimpleMetric()
    for preds, gt, ys in _cases():
        single.update([preds], [gt], [ys])
    expected = {k: float(v) for k, v in single.compute().items()}
    half = TuSimpleMetric()
    for preds, gt, ys in _cases()[0::2]:
        half.update([preds], [gt], [ys])
    assert abs(float(half.compute()["Accuracy"]) - expected["Accuracy"]) > 1e-6  # halves differ from the whole
    for rank in range(2):
        got = json.loads((tmp_path / f"rank{rank}.json").read_text())
        for key, value in expected.items():
            assert abs(got[key] - value) < 1e-9, (rank, key)


def test_ddp_cli_run_two_cpu_processes(tmp_path):
    run_dir = tmp_path / "run"
    run_cli([*TINY, "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.max_steps=2",
             "trainer.limit_val_batches=1"], run_dir)
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 2
    records = read_records(run_dir / "per_image.jsonl")  # both ranks' records, merged into one file
    assert [r["case_id"] for r in records] == [f"sim-{1000000 + i:07d}" for i in range(4)]
    assert not list(run_dir.glob("per_image.rank*"))
    reported = json.loads((run_dir / "test_scores.json").read_text())[0]
    assert reported["images"] == 4
    assert abs(reported["Accuracy"] - 100 * np.mean([r["accuracy"] for r in records])) < 1e-6
    assert abs(reported["FN"] - 100 * np.mean([r["fn"] for r in records])) < 1e-6
