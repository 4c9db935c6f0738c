"""task=search: the worst natural illusion, a black-box search over one illusion's physical parameters.

The space is the illusion's `Illusion.parameters()` (illusions/parameters.py): every parameter its five severity
levels vary, bounded by the range they span (ints for counts, floats for the rest; the fixed ones are not searched).
Each trial renders the illusion at one point of that space and scores it on task.scenes held-out scenes (seeds
task.search_seed, ...: neither the closed loop's test cases from task.first_seed nor the simulated splits):

- objective=closed_loop: the car drives through each scene as in task=closed_loop (closed_loop/episode.py, the same
  start before the illusion region, control rate, vehicle and lane keeper), and the trial's value is the mean over
  the scenes of the peak |deviation| from the lane centre (m) within the attack window (task.window_s after
  entering the region; over the whole run if the car never entered it);
- objective=open_loop: a detector predicts the lanes of each scene's image, and the value is the F1 drop (TuSimple
  F1, points) from clean to the illusion at the point.

The search maximises the value with Optuna's TPE sampler: a bounded space of mixed ints and floats, few trials (each
drives several runs), no gradient. CMA-ES would need the ints relaxed to floats, and Hydra's Optuna sweeper sweeps
config values one process per trial, not points of an object's own space. The study lives in <out>/study.jsonl:
every finished trial (its point and value) and every comparison value, one JSON line each as it finishes; a rerun
with the same task.out_dir rebuilds the Optuna study from it and runs the trials still missing of task.trials (the
sampler seeded with task.sampler_seed + the finished trials, so a resumed study draws new points), and refuses other
settings (study.run.json). A plain file, not Optuna's SQLite storage: the Optuna that hydra-optuna-sweeper allows
(2.10) cannot create an SQLite study with SQLAlchemy 2. The comparisons (task.severities and clean on the same
scenes, and the best point, the severities and clean re-scored on the test cases) are kept there too, so a rerun
computes only what changed.
"""

from __future__ import annotations

import csv
import json
import math
import warnings
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from lanevil_train.closed_loop.collisions import obstacles
from lanevil_train.closed_loop.episode import LoopSettings, Run, case_scene, drive
from lanevil_train.closed_loop.protocol import Protocol
from lanevil_train.closed_loop.run_scores import entry_time, in_window
from lanevil_train.evaluation.streaming import claim_results
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.illusions.context import context_from_scene
from lanevil_train.illusions.parameters import Parameter
from lanevil_train.illusions.registry import Illusion, get_illusion
from lanevil_train.lanes import default_h_samples
from lanevil_train.models.detector import TUSIMPLE_WIDTH
from lanevil_train.results_log import ResultsLog
from lanevil_train.tasks.builders import output_dir
from lanevil_train.tasks.closed_loop import ClosedLoopSettings, build_policies, policy_kind
from lanevil_train.tasks.search_settings import OBJECTIVES, SearchSettings

STUDY = "study.jsonl"
Variant = Mapping | int  # what a scene is scored with: a point of the illusion's space, or a severity (0: clean)


# ---------------------------------------------------------------------------------------- objectives
def window_peak(trace: list[dict], region_start_m: float, window_s: float) -> float:
    """The largest |deviation| (m) of the steps within the attack window; of every step if the car never entered
    the illusion region."""
    entry = entry_time(trace, region_start_m)
    steps = [step for step in trace if entry is not None and in_window(step["t"], entry, window_s)]
    return max(abs(step["deviation"]) for step in (steps or trace))


class ClosedLoopScore:
    """The mean peak |deviation| (m) in the attack window over closed-loop runs, one per scene and repeat."""

    def __init__(self, policy, loop: LoopSettings, protocol: Protocol, seed: int):
        self.policy, self.loop = policy, loop
        self.runs = [run for run in protocol.runs(seed, loop.size) if run.severity == 0]  # each start's clean twin

    def __call__(self, variant: Variant) -> float:
        peaks = []
        for run in self.runs:
            # what the radar sees (with task.longitudinal=acc): the objects of a standing illusion at this variant
            objects = obstacles(case_scene(run.seed, self.loop.size)[0], run.illusion, variant, run.seed)
            trace = drive(_with(run, variant), self.policy, self.loop, objects)
            peaks.append(window_peak(trace, run.region[0], self.loop.window_s))
        return float(np.mean(peaks))


def _with(run: Run, variant: Variant) -> Run:
    """The run with the illusion at a point, at a severity, or clean (severity 0)."""
    if isinstance(variant, Mapping):
        return replace(run, severity=0, point=tuple(variant.items()))
    return replace(run, severity=int(variant))


class OpenLoopScore:
    """The F1 drop (TuSimple F1, points) of a detector's lanes from the clean scenes to the illusion's."""

    def __init__(self, policy, illusion: Illusion, seeds: list[int], size: tuple[int, int]):
        self.policy, self.illusion = policy, illusion
        self.samples = []  # (seed, clean image, true lanes in pixels, context) of each scene
        for seed in seeds:
            scene, image = case_scene(seed, size)
            self.samples.append((seed, image, scene.lanes()[0], context_from_scene(scene)))
        self.height, self.width = size
        self.clean_f1 = self.f1(0)

    def f1(self, variant: Variant) -> float:
        """TuSimple F1 (%) of the detector over the scenes, with the illusion at `variant` (0: clean)."""
        from lanevil_train.metrics import tusimple_lane_scores, tusimple_summary

        sums = np.zeros(3)
        for seed, image, lanes, ctx in self.samples:
            shown = _render(self.illusion, image, ctx, variant, seed)
            sums += tusimple_lane_scores(self.policy.lanes(shown), lanes, default_h_samples(self.height),
                                         pixel_thresh=20.0 * self.width / TUSIMPLE_WIDTH)
        return 100.0 * tusimple_summary(*sums, len(self.samples))["F1"]

    def __call__(self, variant: Variant) -> float:
        return self.clean_f1 - self.f1(variant)


def _render(illusion: Illusion, image: np.ndarray, ctx, variant: Variant, seed: int) -> np.ndarray:
    """The image with the illusion at a point or a severity (unchanged for severity 0)."""
    if isinstance(variant, Mapping):
        return illusion.render_point(image, ctx, variant, seed)
    return illusion(image, ctx, variant, seed) if variant else image


def scorer(settings: SearchSettings, policy, loop: LoopSettings, protocol: Protocol, seed: int) -> Callable:
    """The objective of `settings` on the scenes of `protocol` (its first_seed and cases)."""
    if settings.objective == "closed_loop":
        return ClosedLoopScore(policy, loop, protocol, seed)
    seeds = [protocol.first_seed + i for i in range(protocol.cases)]
    return OpenLoopScore(policy, get_illusion(settings.illusion), seeds, loop.size)


# ---------------------------------------------------------------------------------------- the study
class Study:
    """The search: an Optuna study (TPE, maximising) whose finished trials and comparison values are kept in
    <out>/study.jsonl, one JSON line each as it finishes; a rerun rebuilds the study from them and runs only the
    trials still missing (a killed trial runs again). study.run.json records the settings; a rerun with others is
    refused."""

    def __init__(self, out: Path, illusion: Illusion, sampler_seed: int, identity: dict):
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        self.illusion = illusion
        self.log = ResultsLog(out / STUDY)
        resuming = bool(self.log.resume())
        claim_results(self.log.path, identity, resuming)
        records = self.log.records() if resuming else []
        self.trials = [record for record in records if record["key"].startswith("trial/")]
        self.values = {record["key"]: record["value"] for record in records if not record["key"].startswith("trial/")}
        # seeded past the finished trials: a resumed study does not draw the first points again
        sampler = optuna.samplers.TPESampler(seed=sampler_seed + len(self.trials))
        self.study = optuna.create_study(direction="maximize", sampler=sampler)
        distributions = {parameter.name: _distribution(parameter) for parameter in illusion.parameters().searched}
        with warnings.catch_warnings():  # Optuna 2 calls create_trial and add_trial experimental
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            for record in self.trials:
                self.study.add_trial(optuna.trial.create_trial(params=record["params"], distributions=distributions,
                                                               value=record["value"]))

    def run(self, score: Callable[[dict], float], trials: int, start: str = "severities") -> None:
        """Run the trials still missing of `trials`, each kept as it finishes, one line printed each; with `start`
        "severities" the severity points (5 down to 1) not yet tried come first (search_settings.STARTS)."""
        missing = trials - len(self.trials)
        if missing <= 0:
            return
        if start == "severities":
            for params in self.severity_points()[:missing]:
                self.study.enqueue_trial(params)

        def objective(trial) -> float:
            point = suggest(trial, self.illusion)
            value = float(score(point))
            record = {"key": f"trial/{trial.number}", "trial": trial.number, "value": value,
                      "params": {name: point[name] for name in trial.params}}
            self.log.append([record])
            self.trials.append(record)
            print(f"trial {trial.number + 1}/{trials}: {value:.4f} (best {self.best['value']:.4f})", flush=True)
            return value

        self.study.optimize(objective, n_trials=missing)

    def severity_points(self) -> list[dict]:
        """The searched parameters of severities 5, 4, ..., 1 that no finished trial has tried yet."""
        searched = [parameter.name for parameter in self.illusion.parameters().searched]
        tried = [record["params"] for record in self.trials]
        points = [{name: self.illusion.point(severity)[name] for name in searched} for severity in range(5, 0, -1)]
        return [point for i, point in enumerate(points) if point not in tried and point not in points[:i]]

    @property
    def best(self) -> dict:
        """The finished trial with the largest value (the first of equal ones)."""
        return max(self.trials, key=lambda record: (record["value"], -record["trial"]))

    def best_point(self) -> dict:
        """The best trial's full point (its searched values and the fixed ones)."""
        return self.illusion.parameters().check(self.best["params"])

    def remembered(self, key: str, compute: Callable[[], float]) -> float:
        """A comparison value kept in the study under `key`, computed once."""
        if key not in self.values:
            self.values[key] = float(compute())
            self.log.append([{"key": key, "value": self.values[key]}])
        return self.values[key]


def _distribution(parameter: Parameter):
    """The Optuna distribution trial.suggest_int / suggest_float records for a parameter (Optuna 2 or 3 names)."""
    import optuna.distributions as dist

    if parameter.kind == "int":
        kind = getattr(dist, "IntDistribution", None) or dist.IntUniformDistribution
        return kind(int(parameter.low), int(parameter.high))
    kind = getattr(dist, "FloatDistribution", None) or dist.UniformDistribution
    return kind(float(parameter.low), float(parameter.high))


def suggest(trial, illusion: Illusion) -> dict:
    """The trial's point: a value for every searched parameter of the illusion (the fixed ones filled in)."""
    values = {}
    for parameter in illusion.parameters().searched:
        if parameter.kind == "int":
            values[parameter.name] = trial.suggest_int(parameter.name, int(parameter.low), int(parameter.high))
        else:
            values[parameter.name] = trial.suggest_float(parameter.name, float(parameter.low), float(parameter.high))
    return illusion.parameters().check(values)


# ---------------------------------------------------------------------------------------- the task
def search(cfg: DictConfig) -> float:
    """Search task.illusion's parameters for the point with the largest objective, resumably; write the trials,
    the best point beside the severities, the plots and the best point re-scored on the test cases; return its
    value on the search scenes."""
    settings = SearchSettings.from_config(cfg.task)
    loop_settings = ClosedLoopSettings.from_config(cfg.task)
    protocol = replace(loop_settings.protocol, illusions=(settings.illusion,))  # the test cases
    check_search(cfg, settings, protocol)
    policy, identity = build_policies(cfg, loop_settings)[0]
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    illusion = get_illusion(settings.illusion)
    held_out = replace(protocol, cases=settings.scenes, first_seed=settings.search_seed)
    score = scorer(settings, policy, loop_settings.loop, held_out, cfg.seed)
    study = Study(out, illusion, settings.sampler_seed, _identity(cfg, identity))
    study.run(score, settings.trials, settings.start)
    compare = comparisons(study, "search", score, protocol.severities)
    write_results(out, study, settings, compare, held_out, loop_settings.loop.size)
    test_score = scorer(settings, policy, loop_settings.loop, protocol, cfg.seed)
    rescored = rescore(out, study, settings, test_score, protocol)
    best = study.best
    print(f"Worst {illusion.name} after {len(study.trials)} trials: {settings.objective} {best['value']:.4f} on the "
          f"search scenes, {rescored['best']:.4f} on the test cases; " +
          ", ".join(f"{name} {value:.4f}" for name, value in compare.items()) + f" ({out / 'best_parameters.json'})")
    return float(best["value"])


def check_search(cfg: DictConfig, settings: SearchSettings, protocol: Protocol) -> None:
    """What the config check cannot see alone: the scenes apart, one model, a detector for open_loop, Optuna."""
    settings.check_scenes(protocol)
    if len(cfg.task.models or {}) > 1:
        raise ValueError(f"task.models: task=search searches for one model, got {len(cfg.task.models)}: give one "
                         f"(or ckpt_path=)")
    if settings.objective == "open_loop" and policy_kind(cfg) != "detector":
        raise ValueError(f"task.objective: open_loop scores a lane detector's lanes; task.policy={policy_kind(cfg)} "
                         f"draws none (give ckpt_path=<checkpoint>, or task.objective=closed_loop)")
    _require_optuna()


def write_results(out: Path, study: Study, settings: SearchSettings, compare: dict, scenes: Protocol,
                  size: tuple[int, int]) -> None:
    """trials.csv, best_parameters.json (the worst point, its value and the comparisons), search.png and
    worst_illusion.png."""
    best, point = study.best, study.best_point()
    write_trials(out / "trials.csv", study.trials, study.illusion)
    write_json(out / "best_parameters.json", {
        "illusion": settings.illusion, "objective": settings.objective, "measure": OBJECTIVES[settings.objective],
        "direction": "maximize", "trials": len(study.trials), "best_trial": best["trial"], "value": best["value"],
        "point": point, **compare,
        "scenes": {"first_seed": scenes.first_seed, "count": scenes.cases, "repeats": scenes.repeats}})
    plot_search(out / "search.png", study.trials, compare, settings)
    write_worst_render(out / "worst_illusion.png", study.illusion, point, scenes.first_seed, size, best["value"],
                       compare.get("severity_3"))


def rescore(out: Path, study: Study, settings: SearchSettings, score: Callable, protocol: Protocol) -> dict:
    """rescore.json: the best point, the compared severities and clean on the test cases (task.cases from
    task.first_seed), so the worst case is not an artefact of the search scenes; its values."""
    best, point = study.best, study.best_point()
    values = {"best": study.remembered(f"test/trial/{best['trial']}", lambda: score(point)),
              **comparisons(study, "test", score, protocol.severities)}
    write_json(out / "rescore.json", {
        "illusion": settings.illusion, "objective": settings.objective, "best_trial": best["trial"], "point": point,
        **values, "cases": {"first_seed": protocol.first_seed, "count": protocol.cases, "repeats": protocol.repeats}})
    return values


def comparisons(study: Study, scenes: str, score: Callable, severities) -> dict:
    """The objective at each compared severity and clean (severity 0) on one set of scenes, kept in the study."""
    values = {f"severity_{s}": study.remembered(f"{scenes}/severity_{s}", lambda s=s: score(s)) for s in severities}
    values["clean"] = study.remembered(f"{scenes}/clean", lambda: score(0))
    return values


def _require_optuna() -> None:
    """Optuna importable (an ImportError saying how to install it otherwise), its alembic quiet in Hydra's log."""
    import logging

    logging.getLogger("alembic").setLevel(logging.WARNING)
    try:
        import optuna  # noqa: F401
    except ImportError as error:
        raise ImportError("task=search needs Optuna: pip install 'lanevil_train[sweep]' (or pip install optuna)") \
            from error


def _identity(cfg: DictConfig, policy_identity: dict) -> dict:
    """What a resumed study must share with the one in the out dir: the settings but trials, out_dir and labels,
    the root seed and the model."""
    task = OmegaConf.to_container(cfg.task, resolve=True)
    for key in ("trials", "out_dir", "label", "animate", "workers", "html"):
        task.pop(key, None)
    return {"settings": json.dumps(task, sort_keys=True), "seed": cfg.seed,
            "policy": json.dumps(policy_identity, sort_keys=True, default=str)}


# ---------------------------------------------------------------------------------------- outputs
def write_json(path: Path, value: dict) -> None:
    atomic_write_text(path, json.dumps(value, indent=1) + "\n")


def write_trials(path: Path, trials: list[dict], illusion: Illusion) -> None:
    """trials.csv: each finished trial's number, value, the best value so far and its searched parameters."""
    names = [parameter.name for parameter in illusion.parameters().searched]
    best = -math.inf
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, ["trial", "value", "best_so_far", *names])
        writer.writeheader()
        for record in trials:
            best = max(best, record["value"])
            writer.writerow({"trial": record["trial"], "value": record["value"], "best_so_far": best,
                             **record["params"]})


def plot_search(path: Path, trials: list[dict], compare: dict, settings: SearchSettings) -> None:
    """search.png: the value of every trial, the best so far, and the compared severities as lines."""
    from lanevil_train.report.plots import plt, save_figure

    numbers = [record["trial"] for record in trials]
    values = [record["value"] for record in trials]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(numbers, values, "o", color="tab:blue", label="trial")
    ax.step(numbers, np.maximum.accumulate(values), where="post", color="tab:red", label="best so far")
    for (name, value), style in zip(compare.items(), ("--", ":", "-.", "--")):
        ax.axhline(value, linestyle=style, color="grey", label=name.replace("_", " "))
    ax.set_xlabel("trial")
    ax.set_ylabel(OBJECTIVES[settings.objective])
    ax.set_title(f"task=search: {settings.illusion}, {settings.scenes} held-out scene(s)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def write_worst_render(path: Path, illusion: Illusion, best: dict, seed: int, size: tuple[int, int],
                       value: float, severity_3: float | None) -> None:
    """worst_illusion.png: the best point's render beside severity 3 on the first search scene."""
    from lanevil_train.report.plots import plt, save_figure

    scene, clean = case_scene(seed, size)
    ctx = context_from_scene(scene)
    panels = [(illusion.render_point(clean, ctx, best, seed), f"worst point ({value:.4g})"),
              (illusion(clean, ctx, 3, seed), "severity 3" + ("" if severity_3 is None else f" ({severity_3:.4g})"))]
    fig, axes = plt.subplots(1, 2, figsize=(10, 10 * size[0] / size[1] / 2 + 0.6))
    for ax, (image, title) in zip(axes, panels):
        ax.imshow(image)
        ax.set_title(f"{illusion.name}: {title}", fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path)
