"""Overhead of running each training as a submitit_local job (lanevil_train.tasks.launch) over running the same
task in the calling process: N trivial jobs (`task=build` of one 90x160 case, 2 images), both ways.

In-process: run_task on each job's composed config, one after the other, in a process whose imports are done (a
warm-up run first). submitit_local: launch_jobs with the N jobs (they start at once, each a fresh interpreter that
unpickles the launcher, composes its config and imports the task's modules). The overhead per job is
(submitit - in-process) / N, in wall seconds and in CPU seconds (the jobs' own, counted once they end: the
figure that does not depend on how busy the machine is). It is mostly each job's interpreter start and imports,
which parallel jobs share the machine's cores for. Also printed: launch_jobs' composition check per job.

Usage: python benchmarks/bench_launch.py [--jobs 1 4] [--repeats 1]
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

BUILD = ["task=build", "task.cases=1", "task.illusions=[rail_shadow]", "task.severities=[1]",
         "data.test.size=[90,160]", "task.workers=0", "progress=none"]


def cpu_seconds(who: int) -> float:
    """User + system CPU seconds of this process (RUSAGE_SELF) or of its ended, waited-for descendants
    (RUSAGE_CHILDREN: submitit's job controllers and, through them, the jobs)."""
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def in_process(count: int, root: Path) -> tuple[float, float]:
    """(wall seconds, CPU seconds) to compose and run `count` build jobs one after the other in this process."""
    from hydra import compose

    from lanevil_train.tasks import run_task

    start, cpu = time.perf_counter(), cpu_seconds(resource.RUSAGE_SELF)
    for k in range(count):
        run_task(compose(config_name="config", overrides=[*BUILD, f"output_dir={root / f'job{k}'}"]))
    return time.perf_counter() - start, cpu_seconds(resource.RUSAGE_SELF) - cpu


def through_submitit(count: int, root: Path) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the jobs and this process) for launch_jobs to run `count` build jobs as
    submitit_local jobs and return their outcomes."""
    from lanevil_train.tasks.launch import launch_jobs

    start = time.perf_counter()
    cpu = cpu_seconds(resource.RUSAGE_SELF) + cpu_seconds(resource.RUSAGE_CHILDREN)
    outcomes = launch_jobs({f"job{k}": BUILD for k in range(count)}, root)
    seconds = time.perf_counter() - start
    cpu = cpu_seconds(resource.RUSAGE_SELF) + cpu_seconds(resource.RUSAGE_CHILDREN) - cpu
    failed = [o for o in outcomes if not o.ok]
    if failed:
        raise RuntimeError(f"job {failed[0].name} failed: {failed[0].error}")
    return seconds, cpu


def composition_check(count: int, root: Path) -> float:
    """Milliseconds per job of the composition check launch_jobs runs before it launches anything."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    from lanevil_train.tasks.launch import _master_config

    master, loader = _master_config(root), GlobalHydra.instance().config_loader()
    start = time.perf_counter()
    for k in range(count):
        loader.load_sweep_config(master, [*BUILD, f"hydra.sweep.dir='{root}'", f"hydra.sweep.subdir='job{k}'"])
    assert HydraConfig.initialized()
    return 1000 * (time.perf_counter() - start) / count


def main() -> None:
    """Print the markdown table of both ways' wall times for each job count."""
    from hydra import compose, initialize_config_module
    from hydra.core.hydra_config import HydraConfig

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--repeats", type=int, default=1, help="runs of each measurement; the fastest is kept")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    rows = []
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"), \
            tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        HydraConfig.instance().set_config(compose(config_name="config", return_hydra_config=True,
                                                  overrides=["hydra/launcher=local", "hydra.launcher.timeout_min=30"]))
        in_process(1, root / "warmup")
        check_ms = composition_check(8, root / "check")
        for count in args.jobs:
            local = min(in_process(count, root / f"in{count}_{r}") for r in range(args.repeats))
            jobs = min(through_submitit(count, root / f"sub{count}_{r}") for r in range(args.repeats))
            rows.append((count, local, jobs))
    print(f"\nmachine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the end\n")
    print("| jobs | in-process wall / CPU (s) | submitit_local wall / CPU (s) | overhead per job, wall / CPU (s) |")
    print("|---|---|---|---|")
    for count, (local, local_cpu), (jobs, jobs_cpu) in rows:
        print(f"| {count} | {local:.1f} / {local_cpu:.1f} | {jobs:.1f} / {jobs_cpu:.1f} | "
              f"{(jobs - local) / count:.1f} / {(jobs_cpu - local_cpu) / count:.1f} |")
    print(f"\nlaunch_jobs' composition check before launching: {check_ms:.0f} ms per job")


if __name__ == "__main__":
    main()
