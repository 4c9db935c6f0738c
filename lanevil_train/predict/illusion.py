"""Illusions on your own frames (task=predict task.illusion=NAME): the ground plane under each frame, recovered
from lanes, and the illusion drawn on it as apply_illusion draws it on a photo.

The lanes a frame's ground comes from are the model's own clean prediction on it, or the frame's labels when
given (a TuSimple label file, task.labels). Each frame's geometry is illusions.recover.context_from_lanes's: a
flat straight road, the camera's pitch and yaw from the lanes' vanishing point, its height from a 3.6 m lane width.
A frame whose lanes give no ground plane (fewer than two usable lanes, lines that do not meet above them) is passed
through: its right half is the clean frame, its record says why, and the run counts it.

Images (a folder or a list) are independent: each gets its own ground and the same layout (task.seed).

A video is a drive: the illusion lies on the road and the car moves over it. Its layout is made once, at a frame
whose ground was recovered (the *anchor*: its camera, road and clean image, which the renderers' placement reads),
and every later frame draws it from the car's pose there: ``s = (frame index - anchor's index) x speed / fps``
metres further along the road (sim.sequence.FrameView; speed ``task.speed_kmh``, 50 km/h by default, a typical
urban-arterial speed: 0.46 m a frame at 30 fps), so the illusion slides toward the camera, down the image, as the
road does. The pose's camera (pitch, yaw, height) and the car's offset from its lane's centre come from each frame's
own lanes, smoothed by an exponential moving average (``task.smoothing``, the weight of the newest frame, 0.3):
the illusion moves with the road and does not jitter with the lane estimate. Every ``task.relayout_m`` metres
(15 m by default: the illusions put their key features 6-12 m ahead, illusions/shadow.py and road_damage.py, so by
then they have passed under the car) a new layout is anchored at the current frame, with the next seed (task.seed +
layouts so far). A lane change moves the ego lane, and the layout keeps to the old one until the next layout.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from lanevil_train.illusions.context import IllusionContext
from lanevil_train.illusions.recover import GroundPlaneError, context_from_lanes
from lanevil_train.illusions.registry import check_seed, check_severity, get_illusion
from lanevil_train.lanes import default_h_samples
from lanevil_train.metrics.tusimple import tusimple_lane_scores
from lanevil_train.rules import check_settings, number
from lanevil_train.sim import Camera
from lanevil_train.sim.sequence import FrameView, PoseCamera

SPEED_KMH = 50.0  # task.speed_kmh's default
RELAYOUT_M = 15.0  # task.relayout_m's default
SMOOTHING = 0.3  # task.smoothing's default
PIXEL_THRESH_AT_1280 = 20.0  # a lane is kept when 85 % of its rows lie this close (TuSimple's rule, scaled by width)


@dataclass(frozen=True)
class IllusionSettings:
    """Which illusion task=predict draws on the frames and how it moves in a video (module docstring)."""

    name: str
    severity: int = 3
    seed: int = 0
    speed_kmh: float = SPEED_KMH
    relayout_m: float = RELAYOUT_M
    smoothing: float = SMOOTHING

    SETTINGS = {"speed_kmh": number(0, 300, low_open=True), "relayout_m": number(0, 1000, low_open=True),
                "smoothing": number(0, 1, low_open=True)}  # smoothing: the newest frame's weight

    def __post_init__(self) -> None:
        get_illusion(self.name)  # a ValueError listing the names
        check_severity(self.severity)
        check_seed(self.seed)
        check_settings(self.SETTINGS, vars(self), "")

    def identity(self) -> dict:
        """What a resumed run must share with the one it resumes."""
        return {"illusion": self.name, "severity": self.severity, "seed": self.seed, "speed_kmh": self.speed_kmh,
                "relayout_m": self.relayout_m, "smoothing": self.smoothing}


@dataclass(frozen=True)
class _View:
    """A camera over a road: what FrameView reads of a Scene."""

    camera: Camera
    road: object


@dataclass(frozen=True)
class _Pose:
    """The camera's rig and the car's offset from its lane's centre (m, + right), as one frame's lanes give them."""

    pitch: float
    yaw: float
    height: float
    lateral: float

    def blend(self, newer: "_Pose", weight: float) -> "_Pose":
        return _Pose(*(old + weight * (new - old) for old, new in zip(
            (self.pitch, self.yaw, self.height, self.lateral),
            (newer.pitch, newer.yaw, newer.height, newer.lateral))))


def _ego_centre(context: IllusionContext) -> float:
    """The lateral offset d (road frame) of the centre of the lane the camera is in: between the two lane lines
    around it, or half a lane beyond the outermost line when the camera is outside them all."""
    lines = np.sort(np.asarray(context.lane_offsets, dtype=np.float64))
    camera_d = -context.road.x0
    right = int(np.searchsorted(lines, camera_d))
    if right == 0:
        return float(lines[0] - context.lane_width / 2)
    if right == len(lines):
        return float(lines[-1] + context.lane_width / 2)
    return float(0.5 * (lines[right - 1] + lines[right]))


def _pose(context: IllusionContext) -> _Pose:
    camera = context.camera
    return _Pose(camera.pitch_deg, camera.yaw_deg, camera.height_m, -context.road.x0 - _ego_centre(context))


@dataclass(frozen=True)
class _Layout:
    """An anchored layout: where (frame index) and how (reference context, its clean image, seed) it was made."""

    index: int
    context: IllusionContext
    image: np.ndarray
    seed: int
    ego_centre: float
    number: int


@dataclass(frozen=True)
class IllusionFrame:
    """One frame with the illusion: the image (BGR, None when passed through), its layout's number (0, 1, ...; None
    for an image of a folder), and why it was passed through (None when drawn)."""

    image: np.ndarray | None
    layout: int | None
    passed_through: str | None


class RoadIllusion:
    """The illusion of `settings` drawn on frames in order: ``apply(image, lanes, index)`` (module docstring).
    `metres_per_frame` is the car's travel between two consecutive frame indices of a video (speed / fps), None
    for independent images."""

    def __init__(self, settings: IllusionSettings, metres_per_frame: float | None = None):
        self.settings = settings
        self.illusion = get_illusion(settings.name)
        self.metres_per_frame = metres_per_frame
        self.pose: _Pose | None = None
        self.layout: _Layout | None = None
        self.layouts = 0

    @classmethod
    def for_video(cls, settings: IllusionSettings, fps: float) -> "RoadIllusion":
        return cls(settings, settings.speed_kmh / 3.6 / fps)

    def apply(self, image: np.ndarray, lanes: list[np.ndarray], index: int | None = None) -> IllusionFrame:
        """The BGR `image` with the illusion on the ground its `lanes` (points in its pixels) give; `index` is the
        frame's index in its video (frames come in order), None for an image of a folder."""
        try:
            context = context_from_lanes([np.asarray(lane, dtype=np.float64).reshape(-1, 2) for lane in lanes],
                                         image.shape[:2])
        except GroundPlaneError as error:
            return IllusionFrame(None, None, f"no ground plane: {error}")
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        if self.metres_per_frame is None or index is None:
            return IllusionFrame(self._render(rgb, context, self.settings.seed), None, None)
        pose = _pose(context)
        self.pose = pose if self.pose is None else self.pose.blend(pose, self.settings.smoothing)
        camera = self._camera(context.camera)
        if self.layout is None or (index - self.layout.index) * self.metres_per_frame >= self.settings.relayout_m:
            road = replace(context.road, x0=-(_ego_centre(context) + self.pose.lateral))
            anchor = replace(context, camera=camera, road=road)
            self.layout = _Layout(index, anchor, rgb, self.settings.seed + self.layouts, _ego_centre(anchor),
                                  self.layouts)
            self.layouts += 1
        layout = self.layout
        travel = (index - layout.index) * self.metres_per_frame
        road = replace(layout.context.road, x0=-(layout.ego_centre + self.pose.lateral))
        view = FrameView(reference=_View(layout.context.camera, layout.context.road), current=_View(camera, road),
                         s0=float(travel))
        frame = replace(layout.context, camera=PoseCamera.of(view), view=view, placement_image=layout.image)
        return IllusionFrame(self._render(rgb, frame, layout.seed), layout.number, None)

    def _camera(self, measured: Camera) -> Camera:
        pose = self.pose
        return Camera(width=measured.width, height=measured.height, hfov_deg=measured.hfov_deg,
                      height_m=float(np.clip(pose.height, 0.2, 20.0)), pitch_deg=float(np.clip(pose.pitch, -30, 30)),
                      yaw_deg=float(np.clip(pose.yaw, -45, 45)))

    def _render(self, rgb: np.ndarray, context: IllusionContext, seed: int) -> np.ndarray:
        return cv2.cvtColor(self.illusion(rgb, context, self.settings.severity, seed), cv2.COLOR_RGB2BGR)


def lane_changes(clean: list[np.ndarray], perturbed: list[np.ndarray], height: int, width: int) -> dict:
    """How the illusion changed a frame's lanes, the clean prediction taken as the truth: ``kept`` (clean lanes
    still found: 85 % of their TuSimple rows within 20 px at 1280 px of width, scaled), ``lost`` (clean lanes no
    longer found), ``added`` (lanes only under the illusion), ``accuracy`` (TuSimple's, of the perturbed lanes
    against the clean ones)."""
    thresh = PIXEL_THRESH_AT_1280 * width / 1280
    accuracy, _, _, kept, added, lost = tusimple_lane_scores(perturbed, clean, default_h_samples(height),
                                                             pixel_thresh=thresh, with_counts=True)
    return {"kept": int(kept), "lost": int(lost), "added": int(added), "accuracy": round(float(accuracy), 6)}


def read_labels(path: str | Path, root: Path) -> dict[str, list[np.ndarray]]:
    """The lanes of each image of a TuSimple label file, by its raw_file (normalised, relative to `root`: the input
    folder, or for a video's frames ``frame_%06d``); errors name the file and line."""
    from lanevil_train.data.formats.tusimple import read_tusimple

    return {os.path.normpath(record["raw_file"].lstrip("/")): record["lanes"]
            for record in read_tusimple(path, root, check_images=False)}


def side_by_side(clean: np.ndarray, perturbed: np.ndarray, left: str, right: str) -> np.ndarray:
    """The two drawn frames beside each other (2W x H), each titled in its top-left corner."""
    out = np.concatenate([clean, perturbed], axis=1)
    width = clean.shape[1]
    scale = max(0.4, 0.8 * width / 1280)
    thickness = max(1, int(round(2 * width / 1280)))
    for x, text in ((0, left), (width, right)):
        (_, text_h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
        origin = (x + int(math.ceil(text_h * 0.5)), int(text_h * 1.6))
        cv2.putText(out, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thickness + 2, cv2.LINE_AA)
        cv2.putText(out, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thickness, cv2.LINE_AA)
    return out
