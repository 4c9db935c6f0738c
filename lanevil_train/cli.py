"""Command line: `python -m lanevil_train [group=option ...] [key=value ...]` (Hydra).

The only place, with tasks/, that sees Hydra configs: it picks the task named by `task=` and
hands it the composed config. `--help` lists the config groups and their options.
"""

from __future__ import annotations

import os

# torch's OpenMP (libgomp) spins 300,000 times at every barrier before its threads sleep: where another process holds
# a core, each barrier then waits on a thread that cannot run, and a CPU run goes about 3x slower (the VLM quickstart's
# training at 1.2 instead of 3.6 steps/s). 1,000 spins keep an idle machine's speed and most of the busy one's
# (2.0 steps/s; benchmarks/RESULTS.md). Set before torch loads; a value the user exported wins; results are the same.
os.environ.setdefault("GOMP_SPINCOUNT", "1000")

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from lanevil_train.tasks import run_task  # noqa: E402


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    """Run the configured task; return its headline number (for Hydra sweepers that optimise it)."""
    return run_task(cfg)


if __name__ == "__main__":
    main()
