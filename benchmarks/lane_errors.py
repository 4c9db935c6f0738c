"""Where a detector's lanes are wrong: each true lane of a per_image.jsonl (task=evaluate's records) paired with the
predicted lane closest to it over their common rows (median |dx|), then

- offset: the pair's mean signed x error (px, in the image's own size), per lane;
- after a line: what is left once a straight line in y is fitted to the error (a lane offset and turned as a
  whole leaves little; a wavy or noisy lane leaves much);
- the pull to the centre: predicted x = a * true x + b per band of rows (a < 1: lanes drawn towards x = b / (1 - a)).

    python benchmarks/lane_errors.py RUN/per_image.jsonl
"""

from __future__ import annotations

import argparse

import numpy as np

from lanevil_train.evaluation.lane_records import read_records


def paired_errors(records: list[dict]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(rows, true x, predicted x) of every true lane and its closest prediction (lanes with no prediction sharing
    3 rows are left out)."""
    pairs = []
    for record in records:
        predictions = [{int(y): x for x, y in lane} for lane in record["pred_lanes"]]
        for lane in record["gt_lanes"]:
            truth = {int(y): x for x, y in lane}
            best = None
            for predicted in predictions:
                rows = sorted(set(truth) & set(predicted))
                if len(rows) < 3:
                    continue
                dx = np.array([predicted[y] - truth[y] for y in rows])
                if best is None or np.median(np.abs(dx)) < best[0]:
                    best = (np.median(np.abs(dx)), rows, predicted)
            if best is not None:
                rows = np.array(best[1], dtype=float)
                pairs.append((rows, np.array([truth[y] for y in best[1]]), np.array([best[2][y] for y in best[1]])))
    return pairs


def summary(records: list[dict]) -> dict[str, float]:
    pairs = paired_errors(records)
    offsets, after_line = [], []
    for rows, truth, predicted in pairs:
        dx = predicted - truth
        offsets.append(abs(dx.mean()))
        design = np.stack([rows, np.ones_like(rows)], axis=1)
        after_line.append(np.abs(dx - design @ np.linalg.lstsq(design, dx, rcond=None)[0]).mean())
    def median(values):
        return float(np.median(values)) if values else float("nan")

    return {"true lanes": sum(len(r["gt_lanes"]) for r in records), "paired": len(pairs),
            "median |offset| px": median(offsets), "median error after a line px": median(after_line)}


def centre_pull(records: list[dict], bands=((0, 400), (400, 550), (550, 10**6))) -> list[str]:
    rows, truth, predicted = (np.concatenate(parts) for parts in zip(*paired_errors(records)))
    lines = []
    for low, high in bands:
        band = (rows >= low) & (rows < high)
        a, b = np.polyfit(truth[band], predicted[band], 1)
        lines.append(f"rows {low}-{min(high, int(rows.max()) + 1)}: predicted x = {a:.3f} x true + {b:.1f}; "
                     f"mean |dx| {np.abs(predicted[band] - truth[band]).mean():.1f} px")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("per_image", help="a per_image.jsonl written by task=evaluate (or a training run's test)")
    records = read_records(parser.parse_args().per_image)
    for key, value in summary(records).items():
        print(f"{key}: {value:.1f}" if isinstance(value, float) else f"{key}: {value}")
    print("\n".join(centre_pull(records)))


if __name__ == "__main__":
    main()
