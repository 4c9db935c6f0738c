"""task=report: one table and one set of plots from several evaluation runs, without running a model."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from lanevil_train.evaluation.lane_records import RESULTS
from lanevil_train.evaluation.results import log_results, write_results
from lanevil_train.report.agreement import CLOSED_LOOP_RUNS
from lanevil_train.tasks.builders import build_logger, output_dir
from lanevil_train.tasks.seed_report import relabels, seed_runs, write_seed_report
from lanevil_train.vlm.answer_scoring.evaluation import PER_ANSWER

RESULT_FILES = (RESULTS, PER_ANSWER)  # a lane detector's per-image scores, a VLM's per-answer scores


def results_files(runs: list[str]) -> list[Path]:
    """Every per_image.jsonl (lane detectors) and per_answer.jsonl (VLMs) under the run directories (a run, an
    evaluation, a training run with its robustness/ suite, a multirun sweep or a compare directory), each file
    once, runs in the order given, a run's files in path order with numbers as numbers (a sweep's job 10 after
    job 9), so a report's rows follow the order of the runs and of a sweep's jobs."""
    files: dict[Path, None] = {}
    for run in map(Path, runs):
        if not run.is_dir():
            raise FileNotFoundError(f"task.runs: {run} is not a directory")
        found = sorted((path for name in RESULT_FILES for path in run.rglob(name)), key=path_order)
        if not found and not closed_loop_files([run]):
            raise FileNotFoundError(f"task.runs: no {' or '.join(RESULT_FILES)} (nor closed-loop {CLOSED_LOOP_RUNS}) "
                                    f"in {run} or its subdirectories")
        files.update(dict.fromkeys(path.resolve() for path in found))
    return list(files)


def closed_loop_files(runs: list[str]) -> list[Path]:
    """Every closed-loop runs.jsonl (task=closed_loop's) under the run directories, each once, in path order."""
    files = (path.resolve() for run in map(Path, runs) for path in sorted(run.rglob(CLOSED_LOOP_RUNS), key=path_order))
    return list(dict.fromkeys(files))


def path_order(path: Path) -> tuple:
    """A sort key reading each path part that is a number as that number: 2 < 10, as Hydra numbers its jobs."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part) for part in path.parts)


def report(cfg: DictConfig) -> float:
    """Combine the runs' per-image results into the report in this run's directory; runs of one model label with
    different seeds also get seeds.md (mean ± std over seeds, gains with intervals: tasks/seed_report.py)."""
    if not cfg.task.runs:
        raise ValueError("task=report needs task.runs=[run_dir, ...] (directories holding per_image.jsonl or "
                         "per_answer.jsonl)")
    files = results_files(list(cfg.task.runs))
    if not files:
        raise FileNotFoundError(f"task.runs: closed-loop runs only; task=report needs evaluate runs "
                                f"({' or '.join(RESULT_FILES)}) too, to compare them with")
    value = write_run_reports(files, output_dir(cfg), baseline=cfg.task.baseline,
                              replicates=int(cfg.task.get("bootstrap", 1000)),
                              confidence=float(cfg.task.get("confidence", 0.95)), seed=int(cfg.seed),
                              html=bool(cfg.task.get("html", True)), closed_loop=closed_loop_files(list(cfg.task.runs)))
    log_results(build_logger(cfg), output_dir(cfg))
    return value


def write_run_reports(files: list[Path], out: Path, baseline: str | None = None, replicates: int = 1000,
                      confidence: float = 0.95, seed: int = 0, html: bool = True,
                      closed_loop: list[Path] | None = None) -> float:
    """The report of several runs' results (write_results), each seed run of a repeated label as its own row, and
    seeds.md when labels repeat, with `html` report.html (its tables, seeds and gallery: report/page/), and with
    closed-loop runs.jsonl files agreement.md (open- vs closed-loop rank correlations: report/agreement.py);
    returns write_results' headline value."""
    groups = seed_runs(files)
    labels = relabels(groups)
    repeated = {label for label, _ in groups}
    table_baseline = baseline
    if baseline in repeated:  # the relative table's mCE baseline: that model's first seed run
        first = next(runs for (label, _), runs in groups.items() if label == baseline)
        table_baseline = labels[next(iter(first.values()))]
    value = write_results(files, out, baseline=table_baseline, labels=labels, html=False)
    from lanevil_train.tasks.cards import write_report_cards

    write_report_cards(files, out, labels, table_baseline, replicates, confidence, seed)
    path = write_seed_report(files, out, baseline, replicates, confidence, seed)
    if path is not None:
        print(f"Seeds: {path} (mean ± std over seeds; gains with {confidence:.0%} intervals)")
    if closed_loop:
        from lanevil_train.report.agreement import write_agreement

        path = write_agreement(files, closed_loop, out, labels, replicates, confidence, seed)
        print(f"Open- vs closed-loop agreement: {path}")
    if html and (out / "report.md").is_file():  # a report of perturbed results (write_report wrote one)
        from lanevil_train.report.page import write_robustness_page

        print(f"Report page: {write_robustness_page(out, files, labels=labels)}")
    return value
