"""task=search's own settings (tasks/search.py), typed and checked before any work; config_check reads their rules.

Kept apart from tasks/search.py, which imports the closed loop and torch, so that checking a config stays light.
"""

from __future__ import annotations

from dataclasses import dataclass

from omegaconf import DictConfig

from lanevil_train.closed_loop.protocol import Protocol
from lanevil_train.illusions.registry import ILLUSIONS
from lanevil_train.rules import check_settings, integer, one_of

# task.objective: what a trial's value measures (the search maximises it)
# how a study begins: severities: its first trials are the illusion's severity points, 5 down to 1 (so the search
# starts from what the fixed levels give and its best is never below severity 5's on the search scenes); random: the
# TPE sampler's own random start
STARTS = ("severities", "random")
OBJECTIVES = {"closed_loop": "peak |deviation| in the attack window (m)", "open_loop": "F1 drop from clean (points)"}


@dataclass(frozen=True)
class SearchSettings:
    """task=search's own settings, checked before any work (the closed-loop ones are ClosedLoopSettings')."""

    SETTINGS = {"illusion": one_of(*ILLUSIONS), "trials": integer(1), "objective": one_of(*OBJECTIVES),
                "scenes": integer(1), "search_seed": integer(0), "sampler_seed": integer(0),
                "start": one_of(*STARTS)}  # task.<name>

    illusion: str
    trials: int
    objective: str
    scenes: int
    search_seed: int
    sampler_seed: int
    start: str = "severities"

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task")

    @classmethod
    def from_config(cls, task: DictConfig) -> SearchSettings:
        return cls(**{name: task[name] for name in cls.SETTINGS})

    def check_scenes(self, protocol: Protocol) -> None:
        """The search scenes must not be test cases: the best point is re-scored on those."""
        search = (self.search_seed, self.search_seed + self.scenes)
        test = (protocol.first_seed, protocol.first_seed + protocol.cases)
        if search[0] < test[1] and test[0] < search[1]:
            raise ValueError(f"task.search_seed: the search scenes [{search[0]}, {search[1]}) overlap the test cases "
                             f"[{test[0]}, {test[1]}) (task.first_seed, task.cases); the best point is re-scored on "
                             f"those, so search on other seeds")
