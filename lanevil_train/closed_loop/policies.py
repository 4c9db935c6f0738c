"""Driving policies for the closed loop: camera image -> front-wheel steering angle.

A policy is anything with `name`, `reset()` (a new run) and `act(observation) -> (steer_rad, info)`, where info is
a small JSON-able dict kept in the run's trace (`lanes`: how many lanes it saw, where that applies), and optionally
`corridor() -> CentreLine | None`: the ego lane as it perceives it after its last `act` (the car's frame), where
the longitudinal control's radar looks for objects (closed_loop/longitudinal.py; None: straight ahead). Three ship:

* DetectorPolicy: a lane detector (a trained LaneDetector, any family) + a LaneKeeper (tracker and controller,
  closed_loop/lane_keeper.py) on its lanes;
* TruthPolicy: the simulator's ground-truth lanes + a LaneKeeper (an oracle, optionally with every lane moved by
  `shift_m` on the ground: a detector that is wrong by a known amount);
* VLMPolicy: a driving VLM (any vlm/ backend) asked DRIVING_QUESTION about the last frames; its answer, read by
  parse_direction, becomes a fixed steering angle left, zero or right (LMDrive-style: the language model decides).
"""

from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lanevil_train.closed_loop.lane_keeper import LaneKeeper
from lanevil_train.closed_loop.tracker import CentreLine
from lanevil_train.rules import check_settings, integer, number, text
from lanevil_train.sim import Camera, Scene

DRIVING_QUESTION = "Should the ego vehicle steer left, keep straight or steer right?"


@dataclass(frozen=True)
class Observation:
    """What a policy sees at one control step: the camera image (uint8 HxWx3 RGB), the car's camera as mounted
    (its calibration, which a real car knows), speed (m/s), time (s) and its front-wheel angle (rad, + right: the
    steering sensor; with the speed, the car's odometry). `scene` is the simulator's posed scene, for oracle
    policies only: a real policy never reads it."""

    image: np.ndarray
    camera: Camera
    speed_mps: float
    t: float
    scene: Scene | None = None
    steer_rad: float = 0.0


class Policy(Protocol):
    name: str

    def reset(self) -> None: ...

    def act(self, observation: Observation) -> tuple[float, dict]: ...


class TruthPolicy:
    """Lane keeping on the scene's true lane lines (each moved by shift_m metres on the ground, + right)."""

    def __init__(self, controller: LaneKeeper | None = None, shift_m: float = 0.0, name: str = "ground-truth"):
        self.controller = controller or LaneKeeper()
        self.shift_m = float(shift_m)
        self.name = name

    def reset(self) -> None:
        self.controller.reset()

    def act(self, observation: Observation) -> tuple[float, dict]:
        scene = observation.scene
        if scene is None:
            raise ValueError("TruthPolicy needs observation.scene (the simulator's posed scene)")
        lanes = [scene.lane_polyline(b.d + self.shift_m) for b in scene.road.boundaries if b.marking != "none"]
        lanes = [lane for lane in lanes if len(lane) >= 2]
        return self.controller.steer(lanes, observation.camera, observation.speed_mps, observation.t,
                                     observation.steer_rad)

    def corridor(self) -> CentreLine | None:
        """The lane keeper's tracked lane (on the true lanes: the true lane, as tracked)."""
        return self.controller.line


class DetectorPolicy:
    """A lane detector's lanes, through a LaneKeeper. `model` is a LaneDetector (eval mode, on its device)."""

    def __init__(self, model, controller: LaneKeeper | None = None, name: str = "detector"):
        self.model = model.eval()
        if "input_size" not in (model.build_config or {}):
            raise ValueError(f"{name}: the checkpoint records no input_size (build config "
                             f"{sorted(model.build_config or {})}); it was not written by this project's task=train")
        self.controller = controller or LaneKeeper()
        self.name = name

    def reset(self) -> None:
        self.controller.reset()

    def lanes(self, image: np.ndarray) -> list[np.ndarray]:
        """The detector's lanes in the image's pixels (the simulator's frames are RGB)."""
        return [lane.points for lane in self.model.predict(image, color="rgb")]

    def act(self, observation: Observation) -> tuple[float, dict]:
        return self.controller.steer(self.lanes(observation.image), observation.camera, observation.speed_mps,
                                     observation.t, observation.steer_rad)

    def corridor(self) -> CentreLine | None:
        """The lane keeper's tracked lane, from the detector's lanes."""
        return self.controller.line


_WORDS = re.compile(r"\b(left|right|straight|keep|stay|maintain|continue)\b")
_NEGATION = re.compile(r"\b(not|never|no|avoid|don't|dont|shouldn't|mustn't)\b(\W+\w+)?\W*$")


def parse_direction(answer: str) -> str | None:
    """'left' | 'straight' | 'right' from a VLM's answer, or None when it names no direction: the first
    direction word counts ("Steer left." -> left, "Keep straight, do not steer right" -> straight; keep, stay,
    maintain and continue mean straight unless a side comes first; a word right after a negation, "do not steer
    left", is skipped); a question's echo of every option
    ("left, straight or right") counts as no answer."""
    if not isinstance(answer, str):
        raise ValueError(f"answer: expected the VLM's text, got {type(answer).__name__}")
    text = answer.lower()
    if re.search(r"\bleft\b.{0,30}\bstraight\b.{0,10}\bor\b.{0,15}\bright\b", text):
        return None
    for match in _WORDS.finditer(text):
        if _NEGATION.search(text[max(0, match.start() - 24):match.start()]):
            continue  # "do not steer left": not an answer of left
        word = match.group(1)
        return word if word in ("left", "right") else "straight"
    return None


class VLMPolicy:
    """A VLM asked `question` about its last `frames` camera images each step; left / straight / right become
    -steer_deg / 0 / +steer_deg of front-wheel angle; an answer naming no direction keeps straight and is counted."""

    # task.vlm.* of task=closed_loop: checked by the constructor and, by key, by the config check before any work
    SETTINGS = {"question": text(), "steer_deg": number(0, 30, low_open=True, high_open=True), "frames": integer(1)}

    def __init__(self, vlm, question: str = DRIVING_QUESTION, steer_deg: float = 0.5, frames: int = 6,
                 name: str | None = None):
        check_settings(self.SETTINGS, {"question": question.strip() if isinstance(question, str) else question,
                                       "steer_deg": steer_deg, "frames": frames}, "task.vlm")
        self.vlm, self.question, self.steer_deg = vlm, question, float(steer_deg)
        self.history: deque[np.ndarray] = deque(maxlen=frames)
        self.name = name or getattr(vlm, "name", "vlm")

    def reset(self) -> None:
        self.history.clear()

    def act(self, observation: Observation) -> tuple[float, dict]:
        if not self.history:  # the first step sees a still clip
            self.history.extend([observation.image] * (self.history.maxlen - 1))
        self.history.append(observation.image)
        answer = self.vlm.answer([list(self.history)], [self.question])[0]
        direction = parse_direction(answer)
        sign = {"left": -1.0, "right": 1.0}.get(direction, 0.0)
        return sign * math.radians(self.steer_deg), {"answer": answer[:200], "direction": direction}

    def corridor(self) -> None:
        """No tracked lane: the radar looks straight ahead (closed_loop/longitudinal.py)."""
        return None
