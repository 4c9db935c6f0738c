"""The closed-loop protocol: which runs are driven and the threshold each is scored with (the paper's ASR).

For every case (scene seed first_seed + i), every illusion and every repeat, the car starts start_before_m
(drawn per repeat and seed) before the illusion region and drives once clean (the twin, severity 0) and once at
each severity. With longitudinal control the runs of an illusion whose objects the radar sees (RADAR_KINDS: the
traffic illusions) start run_up_m further back, so the car can stop for them (closed_loop/longitudinal.py). A
run is an attack success when the car leaves the lane centre by more than threshold_m (closed_loop/run_scores.py).
task=closed_loop builds one Protocol from task.* and passes it down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lanevil_train.closed_loop.episode import Run, illusion_region
from lanevil_train.closed_loop.longitudinal import RADAR_KINDS
from lanevil_train.closed_loop.run_scores import ASR_THRESHOLD_M
from lanevil_train.data.illusion_set import Plan
from lanevil_train.rules import check_settings, integer, number, number_range
from lanevil_train.taxonomy import ILLUSION_NAMES


@dataclass(frozen=True)
class Protocol:
    """Cases, illusions, severities and repeats driven, where each run starts, and the success threshold (m)."""

    # task.<name> of task=closed_loop; severities and repeats have the suites' ranges (data/illusion_set.Plan)
    SETTINGS = {"cases": integer(0), "first_seed": integer(0), "severities": Plan.SETTINGS["severities"],
                "repeats": Plan.SETTINGS["repeats"], "start_before_m": number_range(0.0),
                "threshold_m": number(0, low_open=True)}

    cases: int = 8
    first_seed: int = 0
    illusions: tuple[str, ...] = ILLUSION_NAMES
    severities: tuple[int, ...] = (1, 2, 3, 4, 5)
    repeats: int = 1
    start_before_m: tuple[float, float] = (5.0, 10.0)
    threshold_m: float = ASR_THRESHOLD_M
    run_up_m: float = 0.0  # added to the start distance of a traffic illusion's runs (not a task key: the loop's)

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task")
        unknown = [name for name in self.illusions if name not in ILLUSION_NAMES]
        if unknown or not self.illusions:
            raise ValueError(f"task.illusions: expected 'all' or illusion names ({', '.join(ILLUSION_NAMES)}), "
                             f"got {list(self.illusions)}")

    def runs(self, seed: int, size: tuple[int, int]) -> list[Run]:
        """Every run in order: case x illusion x repeat, the clean twin then each severity; `seed` (the run's
        root seed) and the case draw each start."""
        low, high = self.start_before_m
        runs = []
        for i in range(self.cases):
            case_seed = self.first_seed + i
            for j, name in enumerate(self.illusions):
                region = illusion_region(case_seed, name, size)
                for repeat in range(self.repeats):
                    rng = np.random.default_rng([seed, case_seed, j, repeat])
                    run_up = self.run_up_m if name in RADAR_KINDS else 0.0
                    start = round(region[0] - float(rng.uniform(low, high)) - run_up, 4)  # as recorded
                    for severity in [0, *self.severities]:
                        runs.append(Run(f"case{i:03d}", case_seed, name, int(severity), repeat, start, region))
        return runs
