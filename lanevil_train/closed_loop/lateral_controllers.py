"""Lateral controllers: the front-wheel angle that follows the ego lane's centre line (a tracker's CentreLine).

Each takes the centre line in the car's frame (x right, z forward, metres from the rear axle), the speed, the
control period and the current front-wheel angle, and returns (angle in rad, + right; info for the trace, with
`target`, the point it steers to, where it has one). Three ship (`task.controller`):

* `pure_pursuit` (Coulter 1992): the target is the centre line's point `lookahead_s` seconds ahead at the car's
  speed (at least `min_lookahead_m`, at most as far as the line is known); the angle is atan(2 L x / (x^2 + z^2))
  for a target at (x, z) from the rear axle: the arc through the target.
* `stanley` (Thrun et al. 2006, Stanley's DARPA Grand Challenge controller): at the front axle (z = L), the
  heading error to the line's tangent plus atan(gain e / (softening + v)) for the cross-track error e (the line's
  x at the front axle).
* `mpc`: a linear model-predictive controller. The kinematic bicycle linearised for small angles over
  `horizon_s` at the control period dt: heading theta_{k+1} = theta_k + v dt / L u_k, lateral
  x_{k+1} = x_k + v dt theta_k + (v dt)^2 / (2 L) u_k (z_k = v dt k), from the car's own pose (0, 0); cost
  sum_k q_lateral (x_k - line.x(z_k))^2 + q_heading (theta_k - atan line.slope(z_k))^2
  + r_steer (u_k - atan(L curvature))^2 + r_rate ((u_k - u_{k-1}) / dt)^2, with the steering limit
  |u_k| <= max_steer and the rate limit |u_k - u_{k-1}| <= max_steer_rate dt (u_{-1}: the current angle) as
  constraints. The unconstrained optimum is a linear solve; when it breaks a limit the constrained problem is
  solved by SLSQP. The first command is applied (receding horizon). OpenPilot plans its lateral path with an
  MPC (its lateral planner, acados); this is the same idea at its simplest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from lanevil_train.closed_loop.tracker import CentreLine
from lanevil_train.rules import check_settings, number
from lanevil_train.sim.vehicle import VehicleParams


@dataclass(frozen=True)
class Limits:
    """The car's wheelbase (m) and steering limits (front-wheel angle in rad, rad per second); by default those of
    sim.vehicle.VehicleParams."""

    wheelbase_m: float = VehicleParams.wheelbase_m
    max_steer_rad: float = math.radians(VehicleParams.max_steer_deg)
    max_steer_rate_rps: float = math.radians(VehicleParams.max_steer_rate_dps)

    @classmethod
    def of(cls, vehicle: VehicleParams) -> Limits:
        """The limits of a simulated car."""
        return cls(vehicle.wheelbase_m, math.radians(vehicle.max_steer_deg), math.radians(vehicle.max_steer_rate_dps))


@dataclass
class PurePursuit:
    """Pure pursuit on the centre line (see the module docstring)."""

    SETTINGS = {"lookahead_s": number(0, low_open=True), "min_lookahead_m": number(0, low_open=True)}

    lookahead_s: float = 0.5
    min_lookahead_m: float = 6.0
    limits: Limits = Limits()

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task.pure_pursuit")

    def steer(self, line: CentreLine, speed_mps: float, dt_s: float, current_rad: float) -> tuple[float, dict]:
        z = max(self.min_lookahead_m, min(self.lookahead_s * speed_mps, line.range_m))
        x = float(line.x(z))
        angle = math.atan2(2.0 * self.limits.wheelbase_m * x, x * x + z * z)
        return angle, {"target": [round(x, 4), round(z, 3)]}


@dataclass
class Stanley:
    """Stanley's controller on the centre line (see the module docstring)."""

    SETTINGS = {"gain": number(0, low_open=True), "softening_mps": number(0)}

    gain: float = 1.0
    softening_mps: float = 1.0
    limits: Limits = Limits()

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task.stanley")

    def steer(self, line: CentreLine, speed_mps: float, dt_s: float, current_rad: float) -> tuple[float, dict]:
        front = self.limits.wheelbase_m
        error = float(line.x(front))
        heading = math.atan(float(line.slope_at(front)))
        angle = heading + math.atan2(self.gain * error, self.softening_mps + speed_mps)
        return angle, {"target": [round(error, 4), round(front, 3)]}


@dataclass
class LinearMPC:
    """The linear MPC on the kinematic model (see the module docstring)."""

    SETTINGS = {"horizon_s": number(0, 10, low_open=True), "q_lateral": number(0, low_open=True),
                "q_heading": number(0), "r_steer": number(0), "r_rate": number(0)}

    horizon_s: float = 1.5
    q_lateral: float = 1.0
    q_heading: float = 10.0
    r_steer: float = 1.0
    r_rate: float = 0.1
    limits: Limits = Limits()

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task.mpc")

    def _problem(self, line: CentreLine, speed: float, dt: float, current: float):
        """The cost as ||A u - b||^2 over the commands u_0..u_{N-1}, and N."""
        n = max(2, int(round(self.horizon_s / dt)))
        wheelbase = self.limits.wheelbase_m
        step = speed * dt
        # theta_k = step / L * sum_{i<k} u_i ; x_k = sum_{i<k} (step * theta_i + step^2 / (2 L) u_i)
        theta = np.zeros((n + 1, n))
        lateral = np.zeros((n + 1, n))
        for k in range(n):
            theta[k + 1] = theta[k]
            theta[k + 1, k] += step / wheelbase
            lateral[k + 1] = lateral[k] + step * theta[k]
            lateral[k + 1, k] += step * step / (2 * wheelbase)
        z = step * np.arange(1, n + 1)
        rate = np.eye(n) - np.eye(n, k=-1)  # u_k - u_{k-1}
        rate_b = np.zeros(n)
        rate_b[0] = current
        rows = [math.sqrt(self.q_lateral) * lateral[1:], math.sqrt(self.q_heading) * theta[1:],
                math.sqrt(self.r_steer) * np.eye(n), math.sqrt(self.r_rate) / dt * rate]
        targets = [math.sqrt(self.q_lateral) * np.asarray(line.x(z)),
                   math.sqrt(self.q_heading) * np.arctan(line.slope_at(z)),
                   math.sqrt(self.r_steer) * np.full(n, math.atan(wheelbase * line.curvature)),
                   math.sqrt(self.r_rate) / dt * rate_b]
        return np.vstack(rows), np.concatenate(targets), rate, rate_b, n

    def plan(self, line: CentreLine, speed_mps: float, dt_s: float, current_rad: float) -> np.ndarray:
        """The planned commands u_0..u_{N-1} (rad) within the steering and rate limits."""
        a, b, rate, rate_b, n = self._problem(line, speed_mps, dt_s, current_rad)
        u = np.linalg.lstsq(a, b, rcond=None)[0]
        limit, step_limit = self.limits.max_steer_rad, self.limits.max_steer_rate_rps * dt_s
        if np.all(np.abs(u) <= limit + 1e-12) and np.all(np.abs(rate @ u - rate_b) <= step_limit + 1e-12):
            return u
        hessian, gradient = a.T @ a, a.T @ b
        constraints = [{"type": "ineq", "fun": lambda v: step_limit - (rate @ v - rate_b), "jac": lambda v: -rate},
                       {"type": "ineq", "fun": lambda v: step_limit + (rate @ v - rate_b), "jac": lambda v: rate}]
        start = np.clip(current_rad + np.clip(u - current_rad, -step_limit, step_limit), -limit, limit)
        result = minimize(lambda v: 0.5 * v @ hessian @ v - gradient @ v, start, jac=lambda v: hessian @ v - gradient,
                          bounds=[(-limit, limit)] * n, constraints=constraints, method="SLSQP",
                          options={"maxiter": 100, "ftol": 1e-12})
        return result.x

    def steer(self, line: CentreLine, speed_mps: float, dt_s: float, current_rad: float) -> tuple[float, dict]:
        u = self.plan(line, speed_mps, dt_s, current_rad)
        z = min(speed_mps * dt_s * len(u), max(line.range_m, 1.0))
        return float(u[0]), {"target": [round(float(line.x(z)), 4), round(z, 3)]}


CONTROLLERS = {"pure_pursuit": PurePursuit, "stanley": Stanley, "mpc": LinearMPC}
