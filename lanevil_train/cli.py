"""Command line: `python -m lanevil_train [group=option ...] [key=value ...]` (Hydra).

The only place, with tasks/, that sees Hydra configs: it picks the task named by `task=` and
hands it the composed config. `--help` lists the config groups and their options.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from lanevil_train.tasks import run_task


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    """Run the configured task; return its headline number (for Hydra sweepers that optimise it)."""
    return run_task(cfg)


if __name__ == "__main__":
    main()
