"""The ego lane over time: a centre line in the car's frame, from each frame's detected lanes and the car's motion.

A tracker turns the ground lanes of one frame (closed_loop/ground.py) into the ego lane's centre line
x(z) = offset + slope z + curvature / 2 z^2 + curvature rate / 6 z^3 (car frame: x right, z forward, metres from
the rear axle), with the lane width and how far ahead it is known (`CentreLine`). Two ship (`task.tracker`):

* `none` (`FrameTracker`): each frame alone, as a driver assist without memory would: the centre between the
  nearest left and right lanes where both are seen a lane width apart; one boundary shifted by half the last
  measured width; nothing seen: no centre line (the controller holds its last steering angle).
* `kalman` (`KalmanLaneTracker`, the default): the state (offset, slope, curvature, curvature rate, width) with
  its covariance: the clothoid lane model of Dickmanns and Mysliwetz (1992), x(z) = offset + slope z +
  curvature z^2 / 2 + rate z^3 / 6, which is also how this project's roads are built. *Predict* with the car's own
  motion since the last frame (distance travelled and yaw, from its speed and its steering angle: odometry, not
  the simulator's road): the car moves ds forward turning by dtheta (+ right), so in the new frame
      offset' = offset + slope ds + curvature ds^2 / 2 + rate ds^3 / 6 - dtheta ds / 2,
      slope' = slope + curvature ds + rate ds^2 / 2 - dtheta,   curvature' = curvature + rate ds,
      rate' = rate,   width' = width,
  with process noise: the curvature rate drifts as white noise (spectral density `curvature_rate_sigma`^2 per
  metre, integrated into the lower terms), the width as a random walk (`width_sigma`^2 per metre), the yaw as the
  gyro's error (`yaw_rate_sigma` rad/s). *Update* with each boundary seen: its x at up to SAMPLES distances over its
  seen span is x(z) -/+ width / 2 (left / right). Its errors are those of a detected lane: mostly the whole lane
  off, turned or bent (a lane seen 20 cm off is off all along), so their covariance is that of an error a + b z + c
  z^2 / 2 with independent a, b, c of standard deviations `offset_sigma_m`, `slope_sigma`, `curvature_sigma`, plus
  `point_sigma_m` independent at each point: one frame is one look at the lane, not six, and the filter does not
  grow overconfident and start rejecting good detections. *Association and gating*: each side takes the detected
  lane nearest its predicted boundary in Mahalanobis distance; a lane beyond the chi-square gate
  (`gate_probability`, as many degrees of freedom as points) is rejected, and counted when it lies within half a
  lane of a boundary, so a line that appears suddenly beside the boundary (a shadow, a repair seam) does not move
  the lane. *Confidence*: 1 after an accepted update, decaying as exp(-dt / `confidence_time_s`) while nothing is
  accepted (the prediction alone carries the lane); under `min_confidence` the lane is lost: no centre line (the
  controller holds its last plan) and the next frame starts the track afresh from the prior (offset 0 +- 2 m, slope
  0 +- 0.2, curvature 0 +- 0.01 / m, curvature rate 0 +- 1e-4 / m^2, width `lane_width_m` +- 0.5 m) with the
  nearest-lanes rule. *Memory*: a detector's errors persist from frame to frame (the same view, the same mistake),
  which no white measurement noise describes: a filter averaging many frames locks onto an early error (a lane
  width seen 0.4 m narrow, kept for the whole run). The filter forgets with time constant `memory_s` (a
  fading-memory filter: the predicted covariance grows by exp(dt / memory_s) each step, so a frame's weight
  halves every 0.7 memory_s).

The noise settings (conf/task/closed_loop.yaml) are measured, not tuned on the test cases:
benchmarks/tracker_noise.py measures the detector's boundary errors against the true lanes on the synthetic
validation scenes (offset, slope, curvature and point sigmas) and the simulator's roads' curvature rates
(curvature_rate_sigma), then drives further validation scenes to choose memory_s and the default controller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import block_diag
from scipy.stats import chi2

from lanevil_train.closed_loop.ground import NEAR_M, GroundLane, nearest_bounds
from lanevil_train.rules import check_settings, number

SAMPLES = 6  # points measured on each boundary (fewer on a short one)
SAMPLE_SPACING_M = 4.0
# before any detection: offset (m), slope, curvature (1/m), its rate (1/m^2: this project's sharpest S-curve,
# 1/180 m reversing over 30 m, has 1.9e-4), width (m)
PRIOR_SIGMA = (2.0, 0.2, 0.01, 1e-4, 0.5)


@dataclass(frozen=True)
class CentreLine:
    """The ego lane's centre line in the car's frame, a clothoid to third order:
    x(z) = offset_m + slope z + curvature / 2 z^2 + curvature_rate / 6 z^3 (m, + right); its width, and how far
    ahead it was seen (m)."""

    offset_m: float
    slope: float
    curvature: float
    width_m: float
    range_m: float
    curvature_rate: float = 0.0

    def x(self, z):
        """The centre line's lateral offset (m, + right) at forward distances z (m)."""
        z = np.asarray(z, dtype=np.float64)
        return self.offset_m + z * (self.slope + z * (self.curvature / 2 + z * self.curvature_rate / 6))

    def slope_at(self, z):
        """dx/dz of the centre line at forward distances z."""
        z = np.asarray(z, dtype=np.float64)
        return self.slope + z * (self.curvature + z * self.curvature_rate / 2)


@dataclass(frozen=True)
class Motion:
    """How the car moved since the last frame: distance (m) and yaw (rad, + right), from odometry; the period (s)."""

    distance_m: float = 0.0
    yaw_rad: float = 0.0
    dt_s: float = 0.0


def _centre_from(left: GroundLane | None, right: GroundLane | None, width_m: float) -> CentreLine:
    """The centre line from one frame's boundaries (at least one), the lane width used for a lone boundary."""
    if left and right:
        (la, lb, lc), (ra, rb, rc) = left.quadratic(), right.quadratic()
        return CentreLine((la + ra) / 2, (lb + rb) / 2, (lc + rc) / 2, ra - la, min(left.z_far, right.z_far))
    lane, sign = (left, 1.0) if left else (right, -1.0)
    a, b, c = lane.quadratic()
    return CentreLine(a + sign * width_m / 2, b, c, width_m, lane.z_far)


@dataclass
class FrameTracker:
    """task.tracker=none: each frame alone (see the module docstring); remembers only the last plausible width."""

    lane_width_m: float = 3.5
    last_width_m: float | None = field(default=None, init=False)

    def reset(self) -> None:
        self.last_width_m = None

    def update(self, lanes: list[GroundLane], motion: Motion) -> tuple[CentreLine | None, dict]:
        left, right = nearest_bounds(lanes)
        if not (left or right):
            return None, {"estimate": "none"}
        line = _centre_from(left, right, self.last_width_m or self.lane_width_m)
        if left and right:
            self.last_width_m = line.width_m
        return line, {"estimate": "both" if left and right else ("left" if left else "right")}


@dataclass
class KalmanLaneTracker:
    """task.tracker=kalman: the ego lane as a Kalman-filtered state (see the module docstring)."""

    SETTINGS = {
        "offset_sigma_m": number(0),
        "slope_sigma": number(0),
        "curvature_sigma": number(0),
        "point_sigma_m": number(0, low_open=True),
        "curvature_rate_sigma": number(0),
        "memory_s": number(0, low_open=True),
        "width_sigma": number(0),
        "yaw_rate_sigma": number(0),
        "gate_probability": number(0, 1, low_open=True, high_open=True),
        "confidence_time_s": number(0, low_open=True),
        "min_confidence": number(0, 1, high_open=True),
    }

    offset_sigma_m: float = 0.108
    slope_sigma: float = 0.0252
    curvature_sigma: float = 0.00114
    point_sigma_m: float = 0.005
    curvature_rate_sigma: float = 3.4e-6
    memory_s: float = 0.2
    width_sigma: float = 0.005
    yaw_rate_sigma: float = 0.005
    gate_probability: float = 0.999
    confidence_time_s: float = 1.0
    min_confidence: float = 0.2
    lane_width_m: float = 3.5
    state: np.ndarray | None = field(default=None, init=False)
    covariance: np.ndarray | None = field(default=None, init=False)
    confidence: float = field(default=0.0, init=False)
    range_m: float = field(default=0.0, init=False)
    rejected: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task.kalman")

    def reset(self) -> None:
        """A new run: no track, nothing rejected yet."""
        self.state = self.covariance = None
        self.confidence, self.range_m, self.rejected = 0.0, 0.0, 0

    def centre_line(self) -> CentreLine | None:
        if self.state is None:
            return None
        offset, slope, curvature, rate, width = (float(v) for v in self.state)
        return CentreLine(offset, slope, curvature, width, self.range_m, rate)

    # -------------------------------------------------------------------------------------------- predict
    def predict(self, motion: Motion) -> None:
        """Move the state into the car's new frame (see the module docstring) and grow its uncertainty."""
        if self.state is None:
            return
        ds, yaw = motion.distance_m, motion.yaw_rad
        transition = np.eye(5)
        for i in range(4):  # the clothoid's Taylor shift: row i gains ds^(k-i) / (k-i)! of each higher term k
            for k in range(i + 1, 4):
                transition[i, k] = ds ** (k - i) / math.factorial(k - i)
        self.state = transition @ self.state - np.array([yaw * ds / 2, yaw, 0.0, 0.0, 0.0])
        q, a = self.curvature_rate_sigma ** 2, abs(ds)
        noise = np.zeros((5, 5))
        for i in range(4):  # white noise in the curvature rate's change, integrated into the lower terms
            for k in range(4):
                power = (3 - i) + (3 - k) + 1
                noise[i, k] = q * a ** power / (math.factorial(3 - i) * math.factorial(3 - k) * power)
        yaw_var = (self.yaw_rate_sigma * motion.dt_s) ** 2
        noise[:2, :2] += yaw_var * np.array([[ds * ds / 4, ds / 2], [ds / 2, 1.0]])
        noise[4, 4] = self.width_sigma ** 2 * a
        fading = math.exp(motion.dt_s / self.memory_s)  # older frames weigh less: their errors persist
        self.covariance = fading * (transition @ self.covariance @ transition.T) + noise
        self.range_m = max(self.range_m - ds, 0.0)
        self.confidence *= math.exp(-motion.dt_s / self.confidence_time_s)

    # --------------------------------------------------------------------------------------------- update
    def _measurement(self, lane: GroundLane, side: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(H, measured x, their covariance) of a boundary on side -1 (left) / +1 (right)."""
        span = lane.z_far - lane.z_near
        count = int(min(SAMPLES, max(2, span // SAMPLE_SPACING_M + 1)))
        z = np.linspace(lane.z_near, lane.z_far, count)
        h = np.stack([np.ones_like(z), z, z * z / 2, z ** 3 / 6, np.full_like(z, side / 2)], 1)
        shape = h[:, :3] * np.array([self.offset_sigma_m, self.slope_sigma, self.curvature_sigma])
        return h, lane.x(z), shape @ shape.T + self.point_sigma_m ** 2 * np.eye(count)

    def _distance(self, measurement) -> float:
        """The squared Mahalanobis distance of a measurement from the prediction, over its gate (<= 1: inside)."""
        h, x, noise = measurement
        innovation = x - h @ self.state
        s = h @ self.covariance @ h.T + noise
        return float(innovation @ np.linalg.solve(s, innovation)) / chi2.ppf(self.gate_probability, len(x))

    def _associate(self, lanes: list[GroundLane]) -> tuple[list, int]:
        """The measurements accepted (one lane per side at most, each the nearest to its predicted boundary, inside
        the gate) and how many lanes were rejected: outside every gate, though within half a lane width of a
        predicted boundary NEAR_M ahead (a lane further out is the next lane's boundary, not a bad detection)."""
        measured = {(i, side): self._measurement(lane, side) for i, lane in enumerate(lanes) for side in (-1.0, 1.0)}
        scores = sorted((self._distance(measurement), side, i) for (i, side), measurement in measured.items())
        chosen, used_sides, used_lanes = [], set(), set()
        for distance, side, i in scores:
            if side in used_sides or i in used_lanes or distance > 1.0:
                continue
            used_sides.add(side)
            used_lanes.add(i)
            chosen.append(measured[i, side] + (lanes[i],))
        line = self.centre_line()
        bounds = [float(line.x(NEAR_M)) + side * line.width_m / 2 for side in (-1.0, 1.0)]
        rejected = sum(1 for i, lane in enumerate(lanes) if i not in used_lanes
                       and min(abs(float(lane.x(NEAR_M)) - bound) for bound in bounds) < line.width_m / 2)
        return chosen, rejected

    def _correct(self, measurements: list) -> float:
        """Update with the stacked measurements; their normalised innovation squared over its degrees of freedom
        (about 1 on average for a filter whose noise settings fit what it sees; kept in the trace as `nis`)."""
        h = np.concatenate([m[0] for m in measurements])
        x = np.concatenate([m[1] for m in measurements])
        r = block_diag(*[m[2] for m in measurements])
        s = h @ self.covariance @ h.T + r
        innovation = x - h @ self.state
        nis = float(innovation @ np.linalg.solve(s, innovation)) / len(x)
        gain = np.linalg.solve(s, h @ self.covariance).T
        self.state = self.state + gain @ (x - h @ self.state)
        identity = np.eye(5)
        self.covariance = (identity - gain @ h) @ self.covariance @ (identity - gain @ h).T + gain @ r @ gain.T
        self.range_m = max(m[3].z_far for m in measurements)
        self.confidence = 1.0
        return nis

    def update(self, lanes: list[GroundLane], motion: Motion) -> tuple[CentreLine | None, dict]:
        """Predict with `motion`, correct with this frame's lanes; (the centre line or None when lost, trace info:
        estimate both | left | right | predicted | none, confidence, rejected so far)."""
        self.predict(motion)
        nis = None
        if self.state is not None and self.confidence < self.min_confidence:
            self.state = self.covariance = None  # lost: start afresh from the next detection
        if self.state is None:
            left, right = nearest_bounds(lanes)
            measurements = [self._measurement(lane, side) + (lane,)
                            for lane, side in ((left, -1.0), (right, 1.0)) if lane is not None]
            if measurements:
                self.state = np.array([0.0, 0.0, 0.0, 0.0, self.lane_width_m])
                self.covariance = np.diag(np.square(PRIOR_SIGMA))
                self._correct(measurements)
        else:
            measurements, rejected = self._associate(lanes)
            self.rejected += rejected
            if measurements:
                nis = self._correct(measurements)
        sides = {m[0][0, 4] for m in measurements}
        estimate = ("both" if len(sides) == 2 else "left" if -0.5 in sides else "right") if measurements else (
            "predicted" if self.state is not None else "none")
        info = {"estimate": estimate, "confidence": round(self.confidence, 4), "rejected": self.rejected,
                "nis": None if nis is None else round(nis, 4)}
        return self.centre_line(), info


TRACKERS = {"kalman": KalmanLaneTracker, "none": FrameTracker}
