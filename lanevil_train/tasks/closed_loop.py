"""task=closed_loop: drive the simulated car through illusions with a trained model steering it; the paper's ASR.

For every case (a scene seed), every illusion of task.illusions and every repeat, the car starts 5-10 m
(task.start_before_m, random per repeat and seed) before the illusion region and drives once with the illusion at
each severity and once clean (the twin): closed_loop/episode.py. With task.longitudinal=acc (the default) an ACC and
emergency brake slow the car for the objects a radar sees in the lane the policy perceives
(closed_loop/longitudinal.py); task.longitudinal=none keeps the paper's constant speed. Each model (ckpt_path, or
several in task.models, label: checkpoint) drives every run. Finished runs are appended to <out>/runs.jsonl with
their scores, after their traces (one JSON line per control step) were written whole to <out>/traces/<model>/; a
rerun with the same out_dir skips them, and a model added to task.models later drives only its own runs (the
settings must be the same). The report (closed_loop.md, asr_by_*.{md,csv,json}, asr.png, deviation.png,
worst_run.gif) is built from runs.jsonl and the traces alone.
"""

from __future__ import annotations

import json
import multiprocessing
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from lanevil_train.closed_loop.collisions import collision
from lanevil_train.closed_loop.episode import (
    LoopSettings,
    Run,
    case_scene,
    drive,
    ego_lane,
    run_obstacles,
)
from lanevil_train.closed_loop.lane_keeper import LaneKeeper, lane_keeper
from lanevil_train.closed_loop.lateral_controllers import Limits
from lanevil_train.closed_loop.longitudinal import AccSettings
from lanevil_train.closed_loop.policies import DetectorPolicy, TruthPolicy, VLMPolicy
from lanevil_train.closed_loop.protocol import Protocol
from lanevil_train.closed_loop.run_scores import run_scores, twin_scores
from lanevil_train.evaluation.streaming import claim_results
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.progress import progress_counter
from lanevil_train.results_log import ResultsLog
from lanevil_train.sim.vehicle import VehicleParams
from lanevil_train.tasks.builders import checkpoint_model, model_label, output_dir
from lanevil_train.tasks.kinds import is_vlm
from lanevil_train.tasks.vlm.builders import build_defended_vlm
from lanevil_train.taxonomy import ILLUSION_NAMES

RUNS = "runs.jsonl"
# every driving process runs the detector's batch of one on one thread: a thread count changes the order of a
# convolution's sums (results differ in the last bits, and a lane a little), so the runs are the same whatever
# task.workers; one thread is also the fastest beside the rendering on a busy machine (benchmarks/RESULTS.md)
DRIVING_THREADS = 1


@dataclass(frozen=True)
class ClosedLoopSettings:
    """task=closed_loop's settings, typed and checked once (``from_config``) and passed down: the loop (image
    size, control rate, windows, vehicle), the protocol (which runs, the threshold) and the lane keeper every
    detector or ground-truth policy steers with (``keeper()``: a new one per policy). Each part owns its ranges."""

    loop: LoopSettings
    protocol: Protocol
    keeper: Callable[[], LaneKeeper]
    workers: int = 1
    animate: bool = True

    @classmethod
    def from_config(cls, task: DictConfig) -> ClosedLoopSettings:
        acc = AccSettings.from_settings(OmegaConf.to_container(task.acc, resolve=True) if task.get("acc") else {},
                                        task.lane_width_m)
        loop = LoopSettings(size=tuple(task.size), control_hz=task.control_hz, window_s=task.window_s,
                            after_s=task.after_s, vehicle=VehicleParams.from_settings(task.vehicle),
                            longitudinal=task.get("longitudinal", "acc"), acc=acc)
        illusions = ILLUSION_NAMES if task.illusions == "all" else tuple(task.illusions)
        protocol = Protocol(cases=task.cases, first_seed=task.first_seed, illusions=illusions,
                            severities=tuple(task.severities), repeats=task.repeats,
                            start_before_m=tuple(task.start_before_m), threshold_m=task.threshold_m,
                            run_up_m=loop.run_up_m())
        named = {name: OmegaConf.to_container(task[name], resolve=True) for name in (task.tracker, task.controller)
                 if name in task and task[name] is not None}
        keeper = partial(lane_keeper, task.tracker, task.controller, Limits.of(loop.vehicle), task.max_range_m,
                         task.lane_width_m, 1.0 / loop.control_hz, named)
        keeper()  # its settings checked here, before any model loads
        return cls(loop, protocol, keeper, workers=max(int(task.workers or 1), 1), animate=bool(task.animate))


def policy_kind(cfg: DictConfig) -> str:
    """task.policy, or by default: vlm for model=vlm/<backend>, else detector."""
    return cfg.task.policy or ("vlm" if is_vlm(cfg) else "detector")


def build_policies(cfg: DictConfig, settings: ClosedLoopSettings) -> list[tuple[object, dict]]:
    """[(policy, identity), ...]: one per model of task.models (label: checkpoint), or the one of ckpt_path, the
    ground truth (task.policy=truth) or the VLM model=vlm/<backend> configures (with its textual defense, e.g.
    defense=pat++ defense.prefix_path=RUN/prefix.json, as task=evaluate applies it)."""
    kind = policy_kind(cfg)
    if kind == "truth":
        return [(TruthPolicy(settings.keeper(), name=cfg.task.label or "ground-truth"), {"policy": "truth"})]
    if kind == "vlm":
        vlm = build_defended_vlm(cfg)  # defense=pat++ defense.prefix_path=... (or self_reminder): as task=evaluate
        policy = VLMPolicy(vlm, cfg.task.vlm.question, cfg.task.vlm.steer_deg, cfg.task.vlm.frames,
                           name=cfg.task.label or vlm.name)
        return [(policy, {"policy": "vlm", **vlm.identity(), **OmegaConf.to_container(cfg.task.vlm)})]
    from lanevil_train.evaluation.streaming import run_identity

    models = dict(cfg.task.models or {})
    if not models:
        if cfg.ckpt_path is None:
            raise ValueError("task=closed_loop needs ckpt_path=/path/to/checkpoint.ckpt, task.models={label: ckpt, "
                             "...}, task.policy=truth (the simulator's own lanes) or model=vlm/<backend>")
        models = {cfg.task.label or "": cfg.ckpt_path}
    out = []
    for label, path in models.items():
        model = checkpoint_model(OmegaConf.merge(cfg, {"ckpt_path": path}))
        label = model_label(model, label)
        policy = DetectorPolicy(model, settings.keeper(), name=label)
        out.append((policy, {"policy": "detector", **run_identity(model, {"model": label})}))
    return out


def trace_path(out: Path, model: str, run_key: str) -> Path:
    """Where a run's trace lives: <out>/traces/<model>/<case>_<illusion>_<severity>_<repeat>.jsonl."""
    return out / "traces" / model / (run_key.replace("/", "_") + ".jsonl")


def read_trace(path: Path) -> list[dict]:
    """A trace file's steps (a record's is at out / record["trace"])."""
    with open(path, encoding="utf-8") as handle:
        return [json.loads(line) for line in handle]


def write_trace(path: Path, trace: list[dict]) -> None:
    """The whole trace or nothing (a kill mid-write leaves no torn trace to be taken as finished)."""
    atomic_write_text(path, "".join(json.dumps(step) + "\n" for step in trace))


def claim_model(out: Path, label: str, identity: dict, resuming: bool) -> None:
    """Record which model drives under `label` (traces/<label>/model.json), or check that the runs already there
    are this same model's: a model added to task.models later drives its runs beside the finished ones."""
    marker = out / "traces" / label / "model.json"
    text = json.dumps(identity, sort_keys=True, indent=1, default=str) + "\n"
    if resuming and marker.is_file() and marker.read_text(encoding="utf-8") != text:
        raise ValueError(f"{out}: the runs of {label!r} there were driven by another model (other weights or "
                         f"settings, {marker}); resuming would report them as this one's: give it another label "
                         f"(task.models / task.label) or another task.out_dir")
    atomic_write_text(marker, text)


def plan_groups(runs: list[Run]) -> list[list[Run]]:
    """The runs in groups of one case, illusion and repeat: the clean twin first, then each severity."""
    groups: dict[tuple, list[Run]] = {}
    for run in runs:
        groups.setdefault((run.case_id, run.illusion, run.repeat), []).append(run)
    return [sorted(group, key=lambda run: run.severity) for group in groups.values()]


def score_run(run: Run, trace: list[dict], twin_trace: list[dict] | None, settings: ClosedLoopSettings) -> dict:
    """A run's scores: the paper's rule from the lane centre, the same rule from the clean twin's path (a perturbed
    run), a collision with a standing illusion, the time-resolved scores (TLC, recovery, false lane lock)."""
    from lanevil_train.closed_loop.time_scores import illusion_edges, time_scores

    loop, threshold = settings.loop, settings.protocol.threshold_m
    scene = case_scene(run.seed, loop.size)[0]
    _, lane_width = ego_lane(scene)
    scores = run_scores(trace, run.region[0], lane_width, threshold, loop.window_s)
    scores.update(time_scores(trace, run.region[0], lane_width, loop.vehicle.speed_mps, scene.road,
                              illusion_edges(run.seed, run.illusion, loop.size), threshold, loop.window_s))
    if twin_trace is not None and run.severity:
        scores.update(twin_scores(trace, twin_trace, run.region[0], threshold, loop.window_s))
    blockers = run_obstacles(run.seed, run.illusion, run.severity, loop.size)
    scores.update(collision(trace, list(blockers), loop.vehicle.wheelbase_m, scores["entry_s"]))
    return {**scores, "lane_width_m": lane_width, "image_size": list(loop.size)}


def drive_group(policy, group: list[Run], settings: ClosedLoopSettings, out: Path, done: frozenset) -> list[dict]:
    """Drive the runs of one group that are not `done` (keys), each trace written whole; their records."""
    records, twin_trace = [], None
    for run in group:
        key = f"{policy.name}|{run.key}"
        path = trace_path(out, policy.name, run.key)
        if key in done:
            if run.severity == 0:
                twin_trace = read_trace(path)
            continue
        trace = drive(run, policy, settings.loop)
        write_trace(path, trace)
        if run.severity == 0:
            twin_trace = trace
        scores = score_run(run, trace, twin_trace, settings)
        records.append({"key": key, "model": policy.name, **run.as_dict(), **scores,
                        "off_road": bool(trace[-1].get("off_road", False)), "steps": len(trace),
                        "trace": str(path.relative_to(out))})
    return records


_WORKER: dict = {}


def _start_worker(cfg: dict) -> None:
    """A worker process: its own models (each process loads them), so the runs it drives are as in one process."""
    import torch

    torch.set_num_threads(DRIVING_THREADS)
    config = OmegaConf.create(cfg)
    settings = ClosedLoopSettings.from_config(config.task)
    _WORKER.update(policies=[policy for policy, _ in build_policies(config, settings)], settings=settings)


def _drive_in_worker(item: tuple[int, list[Run], Path, frozenset]) -> list[dict]:
    index, group, out, done = item
    return drive_group(_WORKER["policies"][index], group, _WORKER["settings"], out, done)


def closed_loop(cfg: DictConfig) -> float:
    """Drive every run with every model, resumably (in task.workers processes); write the report; return the first
    model's ASR (%) under illusions."""
    settings = ClosedLoopSettings.from_config(cfg.task)
    policies = build_policies(cfg, settings)
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    runs = settings.protocol.runs(cfg.seed, settings.loop.size)
    log = ResultsLog(out / RUNS)
    done = log.resume()
    settings_identity = OmegaConf.to_container(cfg.task, resolve=True)
    for key in ("out_dir", "models", "label", "policy", "animate", "workers"):  # may change between reruns
        settings_identity.pop(key, None)
    claim_results(log.path, {"settings": json.dumps(settings_identity, sort_keys=True), "seed": cfg.seed}, bool(done))
    for policy, _identity in policies:
        claim_model(out, policy.name, _identity, any(key.startswith(f"{policy.name}|") for key in done))
    groups = plan_groups(runs)
    items = []
    for index, (policy, _) in enumerate(policies):
        for group in groups:
            keys = frozenset(f"{policy.name}|{run.key}" for run in group)
            if keys - done:
                items.append((index, group, out, frozenset(keys & done)))
    total = len(runs) * len(policies)
    bar = progress_counter(total, len(done), "closed loop", "run", cfg.get("progress", "auto"))
    workers = min(settings.workers, max(len(items), 1))
    pool, threads = None, torch.get_num_threads()
    torch.set_num_threads(DRIVING_THREADS)
    if workers > 1:
        context = multiprocessing.get_context("spawn")  # no forked copy of a model's threads
        pool = context.Pool(workers, _start_worker, (OmegaConf.to_container(cfg, resolve=True),))
        results = pool.imap(_drive_in_worker, items)  # in the planned order, whichever process finishes first
    else:
        results = (drive_group(policies[index][0], group, settings, out, skip)
                   for index, group, out, skip in items)
    try:
        for records in results:
            log.append(records)
            bar.update(len(records), note=f"{records[-1]['key']}" if records else "")
    finally:
        if pool is not None:
            pool.terminate()
        torch.set_num_threads(threads)
    bar.close()
    return write_report(cfg, out, settings)


def write_report(cfg: DictConfig, out: Path, settings: ClosedLoopSettings) -> float:
    """closed_loop.md with its tables and plots, worst_run.gif (task.animate) and report.html (task.html); the
    first model's ASR (%)."""
    from lanevil_train.report.closed_loop import asr_rows, worst_pairs, write_closed_loop_report
    from lanevil_train.report.tables import print_table

    records = ResultsLog(out / RUNS).records()
    protocol, loop = settings.protocol, settings.loop
    shown = {"cases": protocol.cases, "repeats": protocol.repeats, "severities": list(protocol.severities),
             "control_hz": loop.control_hz, "window_s": loop.window_s, "threshold_m": protocol.threshold_m,
             "speed_mph": loop.vehicle.settings()["speed_mph"],
             "longitudinal": loop.longitudinal}  # collisions are counted with this longitudinal control
    path = write_closed_loop_report(records, lambda record: read_trace(out / record["trace"]), out, shown)
    rows = asr_rows(records, "category")
    print_table(rows, f"Closed loop: ASR (%) per illusion category ({path})", digits=1)
    pairs = worst_pairs(records)
    if settings.animate and pairs:
        from lanevil_train.closed_loop.animation import write_animation

        worst, twin = max(pairs, key=lambda pair: pair[0]["max_deviation_m"])
        write_animation([(_run_of(r), read_trace(out / r["trace"]), r["entry_s"]) for r in (worst, twin)],
                        loop.size, out / "worst_run.gif", fps=loop.control_hz)
    if cfg.task.get("html", True):
        from lanevil_train.report.page import write_closed_loop_page

        print(f"Report page: {write_closed_loop_page(out, shown)}")
    first = next(row for row in rows if row["category"] == "all")
    return float(first["ASR (%)"])


def _run_of(record: dict) -> Run:
    return Run(record["case_id"], record["seed"], record["illusion"], record["severity"], record["repeat"],
               record["start_m"], tuple(record["region_m"]))
