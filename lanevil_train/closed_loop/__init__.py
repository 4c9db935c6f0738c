"""Closed loop: a lane-keeping car in the simulator, steered by a policy from its camera, driven through illusions.

sim.vehicle moves the car (kinematic bicycle); episode.drive renders each step from the car's pose and runs the
policy (policies: a lane detector or the ground truth through a lane keeper: ground lanes, a tracker, a controller;
a VLM); run_scores gives the paper's attack success rule and the deviation and departure scores, time_scores the
time-resolved ones (time to line crossing, recovery, false lane lock); protocol.Protocol
plans the grid of cases, illusions, severities and repeats, which tasks/closed_loop.py drives, resumable, and
report/closed_loop.py writes its tables and plots.
"""

from lanevil_train.closed_loop.episode import LoopSettings, Run, drive
from lanevil_train.closed_loop.lane_keeper import LaneKeeper, lane_keeper
from lanevil_train.closed_loop.lateral_controllers import LinearMPC, PurePursuit, Stanley
from lanevil_train.closed_loop.policies import (
                                                DRIVING_QUESTION,
                                                DetectorPolicy,
                                                Observation,
                                                TruthPolicy,
                                                VLMPolicy,
                                                parse_direction,
)
from lanevil_train.closed_loop.protocol import Protocol
from lanevil_train.closed_loop.run_scores import ASR_THRESHOLD_M, ASR_WINDOW_S, run_scores
from lanevil_train.stats import wilson_interval

__all__ = ["LaneKeeper", "lane_keeper", "LinearMPC", "PurePursuit", "Stanley", "LoopSettings", "Run", "drive",
           "Protocol", "DRIVING_QUESTION", "DetectorPolicy", "Observation", "TruthPolicy", "VLMPolicy",
           "parse_direction",
           "ASR_THRESHOLD_M", "ASR_WINDOW_S", "run_scores", "wilson_interval"]
