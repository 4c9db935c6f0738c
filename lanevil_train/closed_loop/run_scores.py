"""Scores of closed-loop runs: the paper's attack success rule, deviations, lane departures, and ASR intervals.

A trace is a list of steps {t (s), s (m along the road), deviation (m from the ego lane's centre, + right), ...}.
Attack success (the paper, after Sato et al. 2021 and AASHTO's lane-keeping margin): the car deviates laterally
by more than `threshold_m` (0.285 m) within `window_s` (2.5 s) of entering the illusion region, i.e. at some step
with entry <= t <= entry + window. The same rule scores a clean twin (same start, no illusion): its successes
are the policy's own failures, the floor the illusion's ASR is read against.

A lane departure is a wheel on a lane line: |deviation| > lane_width / 2 - half_width_m (a car 1.8 m wide);
departures count the steps where the car goes from inside to departed.

Twin-relative rule (twin_scores): the same rule on the run's lateral offset from its clean twin's path at the same
arc length (twin_deviation), so a policy's own drift, which the twin shares, does not count and a drift that
stays inside the 0.285 m lane margin but leaves the twin's path does.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

ASR_THRESHOLD_M = 0.285
ASR_WINDOW_S = 2.5
HALF_CAR_WIDTH_M = 0.9


def entry_time(trace: Sequence[dict], region_start_m: float) -> float | None:
    """When the car first reaches the illusion region (linear between steps), None if it never does."""
    for before, after in zip(trace, trace[1:]):
        if before["s"] >= region_start_m:
            return float(before["t"])
        if after["s"] >= region_start_m:
            part = (region_start_m - before["s"]) / (after["s"] - before["s"])
            return float(before["t"] + part * (after["t"] - before["t"]))
    if trace and trace[-1]["s"] >= region_start_m:
        return float(trace[-1]["t"])
    return None


def attack_fired_at(trace: Sequence[dict], entry_s: float | None, threshold_m: float = ASR_THRESHOLD_M,
                    window_s: float = ASR_WINDOW_S, deviations: Sequence[float] | None = None) -> float | None:
    """The first time within [entry, entry + window] that |deviation| exceeds threshold_m, else None.

    `deviations` (one per step) replaces the steps' own lane deviations, e.g. twin_deviation's."""
    if entry_s is None:
        return None
    if deviations is None:
        deviations = [step["deviation"] for step in trace]
    elif len(deviations) != len(trace):
        raise ValueError(f"attack_fired_at: {len(deviations)} deviations for {len(trace)} steps")
    for step, deviation in zip(trace, deviations):
        if in_window(step["t"], entry_s, window_s) and abs(deviation) > threshold_m:
            return float(step["t"])
    return None


def in_window(t: float, entry_s: float, window_s: float = ASR_WINDOW_S) -> bool:
    """Whether time t (s) lies in the attack window [entry, entry + window], both ends included (to 1 ns)."""
    return entry_s - 1e-9 <= t <= entry_s + window_s + 1e-9


def departures(trace: Sequence[dict], lane_width_m: float, half_width_m: float = HALF_CAR_WIDTH_M) -> list[float]:
    """The times the car goes from inside its lane to a wheel on a lane line."""
    limit = lane_width_m / 2.0 - half_width_m
    out, inside = [], True
    for step in trace:
        departed = abs(step["deviation"]) > limit
        if departed and inside:
            out.append(float(step["t"]))
        inside = not departed
    return out


def run_scores(trace: Sequence[dict], region_start_m: float, lane_width_m: float,
               threshold_m: float = ASR_THRESHOLD_M, window_s: float = ASR_WINDOW_S) -> dict:
    """One run's scores: success (the ASR rule), when it fired (s after entry), the largest |deviation| (m),
    the first lane departure (s after entry; None if none), departures and departures per km driven."""
    if not trace:
        raise ValueError("run_scores: an empty trace")
    entry = entry_time(trace, region_start_m)
    fired = attack_fired_at(trace, entry, threshold_m, window_s)
    times = departures(trace, lane_width_m)
    distance_km = max(trace[-1]["s"] - trace[0]["s"], 1e-9) / 1000.0
    after_entry = [t - entry for t in times if entry is not None and t >= entry - 1e-9]
    return {
        "entered": entry is not None,
        "entry_s": None if entry is None else round(entry, 4),
        "success": fired is not None,
        "fired_after_s": None if fired is None else round(fired - entry, 4),
        "max_deviation_m": round(max(abs(step["deviation"]) for step in trace), 4),
        "first_departure_s": round(after_entry[0], 4) if after_entry else None,
        "departures": len(times),
        "departures_per_km": round(len(times) / distance_km, 3),
        "distance_m": round(distance_km * 1000.0, 3),
    }


def twin_deviation(trace: Sequence[dict], twin_trace: Sequence[dict]) -> list[float]:
    """Per step of `trace`, its lateral offset d minus its clean twin's d at the same arc length s (m, + right).

    The twin's d is interpolated linearly over its s; a step before the twin's first s or beyond its last one takes
    the twin's d at that end (its first or last step), so a run that drives on after its twin stopped is compared
    with where the twin last was. The twin's s must not decrease (the car drives forward); where it stood still
    (equal s, a car braked to a stop), the last of those steps counts."""
    if not twin_trace:
        raise ValueError("twin_deviation: an empty twin trace")
    twin_s = np.array([step["s"] for step in twin_trace], np.float64)
    twin_d = np.array([step["d"] for step in twin_trace], np.float64)
    last = np.append(np.diff(twin_s) != 0, True)  # the last step of each run of equal s
    twin_s, twin_d = twin_s[last], twin_d[last]
    if np.any(np.diff(twin_s) <= 0):
        raise ValueError("twin_deviation: the twin's arc length s must increase from step to step")
    at = np.interp([step["s"] for step in trace], twin_s, twin_d)
    return [float(step["d"] - ref) for step, ref in zip(trace, at)]


def twin_scores(trace: Sequence[dict], twin_trace: Sequence[dict], region_start_m: float,
                threshold_m: float = ASR_THRESHOLD_M, window_s: float = ASR_WINDOW_S) -> dict:
    """The attack success rule on the deviation from the clean twin (twin_deviation) instead of from the lane
    centre: twin_success (|twin deviation| > threshold_m at a step within window_s of the run's entering the
    region), twin_fired_after_s (s after entry; None if it did not fire) and twin_max_deviation_m (the largest
    |twin deviation| over the run, m). A twin scored against itself gives False, None and 0."""
    if not trace:
        raise ValueError("twin_scores: an empty trace")
    deviation = twin_deviation(trace, twin_trace)
    entry = entry_time(trace, region_start_m)
    fired = attack_fired_at(trace, entry, threshold_m, window_s, deviations=deviation)
    return {
        "twin_success": fired is not None,
        "twin_fired_after_s": None if fired is None else round(fired - entry, 4),
        "twin_max_deviation_m": round(max(abs(v) for v in deviation), 4),
    }
