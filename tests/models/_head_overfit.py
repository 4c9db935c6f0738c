"""A family's head fitted alone to a few simulated scenes: the quick check that its loss, targets and decoding agree.

A random ResNet-18 is frozen and its features computed once (batch statistics, no gradient); the family's neck and
head train on them with the family's own optimizer, rate multipliers, schedule and gradient clipping (its config's
rate scaled to the batch as a run would), then decode the same scenes. A head whose loss rewards the wrong thing
(UFLD's old similarity loss), that collapses (LaneFormer at one large rate) or whose decoding drops lanes
(BezierLaneNet's old window) scores far below its working self here. The fit runs on one thread with torch's
deterministic algorithms (the scenes are one batch, so the data order is fixed too): the same seed gives the same
figures on one machine and torch; on another CPU the float sums may still round differently, so each family test
sets its bound from the spread over seeds 0-4 measured here (in its docstring), not from one run. Used by the
family tests and by hand:

    python -m tests.models._head_overfit ufld --steps 200
"""

from __future__ import annotations

import argparse
import contextlib

import numpy as np
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from lanevil_train.data.datasets import SyntheticLaneDataset
from lanevil_train.data.transforms import LaneSampleProcessor
from lanevil_train.lanes import default_h_samples
from lanevil_train.metrics import tusimple_lane_scores
from lanevil_train.models.detector import TUSIMPLE_WIDTH
from lanevil_train.models.head import targets_to
from lanevil_train.models.schedules import scaled_lr
from lanevil_train.tasks.builders import build_model, model_config

FIRST_SEED = 4000  # scenes of the train range, away from the seeds other tests render
CROP_TOP = 0.4     # the quickstarts' sky cut


def _config(overrides: list[str]):
    if GlobalHydra.instance().is_initialized():  # inside the tests' hydra_conf fixture
        return compose(config_name="config", overrides=overrides)
    with initialize_config_module(config_module="lanevil_train.conf", version_base=None):
        return compose(config_name="config", overrides=overrides)


def _batch(family_cfg, model, seeds: list[int], size: tuple[int, int]) -> dict:
    processor = LaneSampleProcessor(size, augment=False, encode=model.head.encode, crop_top=CROP_TOP)
    items = [processor(SyntheticLaneDataset(1, first_seed=seed, size=(360, 640))[0]) for seed in seeds]
    targets = {key: torch.from_numpy(np.stack([item["target"][key] for item in items])) for key in items[0]["target"]}
    return {"images": torch.from_numpy(np.stack([item["image"] for item in items])), "targets": targets,
            "input_lanes": [item["input_lanes"] for item in items]}


def _optimizer(model, steps: int, batch: int, lr: float | None):
    optimizer = model.optimizer_factory(model.parameter_groups())
    for group in optimizer.param_groups:
        rate = lr if lr is not None else group["lr"]
        if lr is None and model.lr_scaling != "none" and model.reference_batch_size:
            rate = scaled_lr(rate, batch, model.reference_batch_size, model.lr_scaling)
        group["lr"] = rate * group["lr_factor"]
    schedule = None if model.scheduler_factory is None else model.scheduler_factory(optimizer, steps)
    return optimizer, schedule


@contextlib.contextmanager
def deterministic():
    """One torch thread and torch's deterministic algorithms inside, both restored after."""
    threads, strict = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(strict)
        torch.set_num_threads(threads)


def head_only_fit(family: str, overrides=(), scenes: int = 8, steps: int = 200, size: tuple[int, int] = (112, 320),
                  lr: float | None = None, seed: int = 0, scene_seeds: list[int] | None = None) -> dict:
    """TuSimple accuracy, FP and FN (in %) of the family's head fitted alone to `scenes` scenes for `steps` steps,
    scored on those scenes in input pixels (the 20 px threshold scaled to the width); also the decoded `lanes`.
    The scenes are seeds FIRST_SEED, FIRST_SEED + 1, ... unless `scene_seeds` lists them; `seed` seeds the weights.
    Deterministic (see the module docstring)."""
    with deterministic():
        return _fit(family, overrides, scenes, steps, size, lr, seed, scene_seeds)


def _fit(family, overrides, scenes, steps, size, lr, seed, scene_seeds) -> dict:
    seeds = list(scene_seeds) if scene_seeds is not None else list(range(FIRST_SEED, FIRST_SEED + scenes))
    cfg = _config([f"model={family}", "backbone=resnet18", f"data.input_size=[{size[0]},{size[1]}]",
                   f"data.crop_top={CROP_TOP}", *overrides])
    torch.manual_seed(seed)
    model = build_model(model_config(cfg))
    batch = _batch(cfg, model, seeds, size)
    model.backbone.requires_grad_(False)
    with torch.no_grad():
        features = [f.detach() for f in model.backbone(batch["images"])]  # batch statistics: a random net's scale
    targets = targets_to(batch["targets"], torch.device("cpu"))
    optimizer, schedule = _optimizer(model, steps, len(seeds), lr)
    trainable = [p for group in optimizer.param_groups for p in group["params"]]
    model.train()
    first_loss = None
    for _ in range(steps):
        mapped = features if model.neck is None else model.neck(features)
        loss = model.head.loss(model.head(mapped), targets)["loss"]
        first_loss = float(loss.detach()) if first_loss is None else first_loss
        optimizer.zero_grad()
        loss.backward()
        if model.gradient_clip_norm is not None:
            torch.nn.utils.clip_grad_norm_(trainable, model.gradient_clip_norm)
        optimizer.step()
        if schedule is not None:
            schedule.step()
    model.eval()
    with torch.no_grad():
        mapped = features if model.neck is None else model.neck(features)
        lanes = model.head.decode(model.head(mapped), **model.decode_kwargs)
    rows = default_h_samples(size[0])
    scores = np.array([tusimple_lane_scores(pred, gt, rows, pixel_thresh=20.0 * size[1] / TUSIMPLE_WIDTH)
                       for pred, gt in zip(lanes, batch["input_lanes"])])
    accuracy, fp, fn = 100.0 * scores.mean(axis=0)
    return {"accuracy": float(accuracy), "fp": float(fp), "fn": float(fn), "lanes": lanes,
            "first_loss": first_loss, "final_loss": float(loss.detach())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("family")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. model.head.sim_loss_weight=0")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--scenes", type=int, default=8)
    parser.add_argument("--lr", type=float, default=None)
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="the scenes' seeds (default: --scenes from "
                        f"{FIRST_SEED})")
    parser.add_argument("--weight-seeds", type=int, nargs="+", default=[0], help="seeds of the weights, one fit each "
                        "(the spread a test's bound is set from: 0 1 2 3 4)")
    args = parser.parse_args()
    for seed in args.weight_seeds:
        out = head_only_fit(args.family, args.overrides, scenes=args.scenes, steps=args.steps, lr=args.lr,
                            seed=seed, scene_seeds=args.seeds)
        print(f"{args.family} seed {seed}: accuracy {out['accuracy']:.1f} %, FP {out['fp']:.1f} %, "
              f"FN {out['fn']:.1f} %, loss {out['first_loss']:.4f} -> {out['final_loss']:.4f}", flush=True)


if __name__ == "__main__":
    main()
