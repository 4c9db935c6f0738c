"""The lane tracker's noise settings, measured (task.kalman.*): how far a detector's ego-lane boundaries lie from
the true ones on the ground, by distance ahead, and how fast the simulator's roads change their curvature.

Usage: python benchmarks/tracker_noise.py CKPT [--scenes 200] [--first-seed 900000] [--size 360 640]

* offset_sigma_m, slope_sigma, curvature_sigma, point_sigma_m: the detector (CKPT) sees the synthetic validation
  scenes (seeds from --first-seed: the validation split, never the closed loop's cases, which are test seeds);
  its lanes and the true lane lines (the scene's own) are back-projected onto the ground as the lane keeper does
  (closed_loop/ground.py).
  Each true ego boundary is paired with the detected lane nearest to it 6 m ahead (within 1 m; else it counts as
  missed); the lateral error is read every 5 m where both are seen. A detected lane's errors along it are not
  independent (a lane seen 20 cm off is 20 cm off all along), so each boundary's errors are fitted with
  a + b z + c z^2 / 2: the spreads of a, b and c are offset_sigma_m, slope_sigma and curvature_sigma, the spread
  of the residuals point_sigma_m. Spreads are robust (1.4826 times the median absolute deviation): the tracker's
  gate, not its noise model, deals with the tails.
* curvature_rate_sigma: the roads' curvature rates j (1/m^2; sim/scene.py: S-curves reverse their curvature over
  s_curve_flip metres, the other roads keep theirs) over as many scenes of the training split; the setting is
  the white-noise density whose drift over the 50 m the car sees equals their spread: std(j) / sqrt(50 m).
* memory_s and the controller: a detector's errors persist from frame to frame (the same view, the same mistake),
  so a filter that averages many frames locks onto an early error (a lane width seen 0.4 m narrow, kept for the
  whole run). The filter forgets with time constant memory_s (fading memory: its covariance grows by
  exp(dt / memory_s) each step). Clean closed-loop drives of further validation scenes (--drives) with the
  measured noise, for each memory_s and controller; the pair with the least mean largest deviation is chosen.
Prints markdown tables and the YAML lines for conf/task/closed_loop.yaml.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from lanevil_train.closed_loop import DetectorPolicy, LoopSettings, Run, drive, lane_keeper
from lanevil_train.closed_loop.episode import illusion_region
from lanevil_train.closed_loop.ground import NEAR_M, ground_lanes
from lanevil_train.models.factory import load_detector
from lanevil_train.sim import build_scene, sample_scene_params, shade_scene
from lanevil_train.sim.scene import road_geometry

DISTANCES = np.arange(5.0, 45.0, 5.0)
PAIR_M = 1.0
SEEN_M = 50.0
CAP_M = 1.0
POINT_FLOOR_M = 0.005  # both lanes are parabolas (ground_lanes' fits), so the residual is nil: a floor


def boundary_errors(policy: DetectorPolicy, seed: int, size: tuple[int, int]) -> tuple[list, int, int]:
    """[[(distance, detected - true x), ...] per paired ego boundary] of one scene, and (boundaries, missed)."""
    scene = build_scene(seed, sample_scene_params(seed), size[1], size[0])
    image = shade_scene(scene)
    detected = ground_lanes(policy.lanes(image), scene.camera, SEEN_M)
    bounds = [b.d for b in scene.road.boundaries]
    ego = scene.params.resolved_ego_lane
    errors, total, missed = [], 0, 0
    for d in (bounds[ego], bounds[ego + 1]):
        truth = ground_lanes([scene.lane_polyline(d)], scene.camera, SEEN_M)
        if not truth:
            continue
        true_lane = truth[0]
        total += 1
        near = [(abs(float(lane.x(NEAR_M) - true_lane.x(NEAR_M))), lane) for lane in detected]
        best = min(near, key=lambda item: item[0], default=None)
        if best is None or best[0] > PAIR_M:
            missed += 1
            continue
        lane = best[1]
        errors.append([(float(z), float(lane.x(z) - true_lane.x(z))) for z in DISTANCES
                       if max(lane.z_near, true_lane.z_near) <= z <= min(lane.z_far, true_lane.z_far)])
    return errors, total, missed


def curvature_rates(scenes: int) -> np.ndarray:
    out = []
    for seed in range(scenes):
        out.append(road_geometry(sample_scene_params(seed)).j)
    return np.asarray(out)


def robust_sigma(values: np.ndarray) -> float:
    """1.4826 x the median absolute deviation from the median: a standard deviation the tails do not widen."""
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


def keeper_study(policy: DetectorPolicy, noise: dict, memories: list[float], controllers: list[str],
                 seeds: range, size: tuple[int, int]) -> list[dict]:
    """Clean closed-loop drives of validation scenes with the measured noise, for each memory_s and controller: the
    largest deviation of each drive (capped at CAP_M: a car that far out has left its lane, further says nothing
    more), its mean and median, the share of drives over the ASR threshold, the tracker's rejections."""
    settings = LoopSettings(size=size)
    rows = []
    for controller in controllers:
        for memory in memories:
            deviations, rejected = [], 0
            for seed in seeds:
                region = illusion_region(seed, "rail_shadow", size)
                run = Run(f"val{seed}", seed, "rail_shadow", 0, 0, region[0] - 7.5, region)
                keeper = lane_keeper("kalman", controller, settings={"kalman": {**noise, "memory_s": memory}})
                policy.controller = keeper
                trace = drive(run, policy, settings)
                rejected += trace[-1]["rejected"]
                deviations.append(min(max(abs(step["deviation"]) for step in trace), CAP_M))
            deviations = np.array(deviations)
            rows.append({"controller": controller, "memory_s": memory, "mean": float(deviations.mean()),
                         "median": float(np.median(deviations)), "over": float((deviations > 0.285).mean()),
                         "rejected": rejected / len(seeds)})
            row = rows[-1]
            print(f"| {controller} | {memory:g} | {row['mean']:.3f} | {row['median']:.3f} | {100 * row['over']:.0f} | "
                  f"{row['rejected']:.1f} |", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt")
    parser.add_argument("--scenes", type=int, default=200)
    parser.add_argument("--first-seed", type=int, default=900000)
    parser.add_argument("--size", type=int, nargs=2, default=[360, 640])
    parser.add_argument("--drives", type=int, default=24, help="validation scenes driven for the memory study")
    parser.add_argument("--memories", type=float, nargs="+", default=[0.2, 0.3, 0.5, 1.0])
    parser.add_argument("--controllers", nargs="+", default=["pure_pursuit", "mpc"])
    args = parser.parse_args()
    policy = DetectorPolicy(load_detector(args.ckpt), name="detector")
    errors, total, missed = [], 0, 0
    for seed in range(args.first_seed, args.first_seed + args.scenes):
        found, n, m = boundary_errors(policy, seed, tuple(args.size))
        errors += found
        total, missed = total + n, missed + m
    lanes = [lane for lane in errors if len(lane) >= 3]
    print(f"{args.scenes} validation scenes, {total} ego boundaries, {missed} missed ({100 * missed / total:.1f} %), "
          f"{len(lanes)} seen at 3 distances or more\n")
    # each boundary's error as a parabola a + b z + c z^2 / 2 (its offset, slope and curvature errors: a lane seen
    # 20 cm off is off all along) and the residual around it
    fits, residuals = [], []
    for lane in lanes:
        z, e = (np.array(v) for v in zip(*lane))
        c2, b, a = np.polyfit(z, e, 2)
        fits.append((a, b, 2 * c2))
        if len(z) >= 5:  # three or four points: a parabola through them leaves no residual to speak of
            residuals += list(e - (a + b * z + c2 * z * z))
    a, b, c = (np.array(v) for v in zip(*fits))
    sigmas = [robust_sigma(v) for v in (a, b, c)]
    inliers = (np.abs(a - np.median(a)) < 3 * sigmas[0]) & (np.abs(b - np.median(b)) < 3 * sigmas[1]) & \
        (np.abs(c - np.median(c)) < 3 * sigmas[2])
    correlation = np.corrcoef(np.stack([a[inliers], b[inliers], c[inliers]]))
    residual = robust_sigma(np.array(residuals))
    rates = curvature_rates(2000)
    density = float(np.std(rates)) / math.sqrt(SEEN_M)
    print("| error of a boundary | median | robust sigma |\n|---|---:|---:|")
    for name, values, sigma in zip(("offset (m)", "slope", "curvature (1/m)"), (a, b, c), sigmas):
        print(f"| {name} | {np.median(values):+.2e} | {sigma:.2e} |")
    print(f"| residual at each distance (m) | | {residual:.3f} |")
    print(f"\ncorrelations of offset, slope, curvature over the {inliers.sum()} boundaries within 3 sigma: "
          f"{np.round(correlation[np.triu_indices(3, 1)], 2).tolist()} (the tracker takes them as independent)")
    print(f"curvature rate over 2000 training roads: std {np.std(rates):.2e} / m^2, "
          f"largest {np.abs(rates).max():.2e}\n")
    print("kalman:")
    print(f"  offset_sigma_m: {sigmas[0]:.3g}")
    print(f"  slope_sigma: {sigmas[1]:.3g}")
    print(f"  curvature_sigma: {sigmas[2]:.3g}")
    print(f"  point_sigma_m: {max(residual, POINT_FLOOR_M):.3g}")
    print(f"  curvature_rate_sigma: {density:.3g}")
    noise = {"offset_sigma_m": sigmas[0], "slope_sigma": sigmas[1], "curvature_sigma": sigmas[2],
             "point_sigma_m": max(residual, POINT_FLOOR_M), "curvature_rate_sigma": density}
    print(f"\nLane keeping on {args.drives} clean validation drives (seeds from {args.first_seed + args.scenes}): the "
          f"largest deviation of each (capped at {CAP_M} m)\n\n| controller | memory_s | mean (m) | median (m) | "
          f"over 0.285 m (%) | rejected per drive |\n|---|---:|---:|---:|---:|---:|")
    seeds = range(args.first_seed + args.scenes, args.first_seed + args.scenes + args.drives)
    rows = keeper_study(policy, noise, args.memories, args.controllers, seeds, tuple(args.size))
    best = min(rows, key=lambda row: row["mean"])
    print(f"\ncontroller: {best['controller']}\nkalman:\n  memory_s: {best['memory_s']:g}   # the least mean largest "
          f"deviation")


if __name__ == "__main__":
    main()
