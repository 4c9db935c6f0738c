"""Our robustness table beside the paper's (LanEvil++ Table main_results): per detector family, the Perturbed /
Original / Gap averages of Accuracy and F1, and the category each one's illusions hurt most.

Usage: python benchmarks/paper_main_table.py REPORT_DIR [--out table.md]
where REPORT_DIR holds robustness/main.json or main.json (a `task=report` or a multirun's report/ directory).
Our rows are matched to the paper's by the family name in the model label (`ganet-resnet18` -> GANet); a family the
paper does not have (CLRerNet) shows our values beside "not in the paper".
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

CATEGORIES = ("road_damage", "traffic_obstruction", "shadow", "reflection")
# The paper's Table main_results: per category (order above) Perturbed, Original, Gap; Accuracy then F1 (%).
PUBLISHED = {
    "laneatt": ("LaneATT", [76.23, 78.66, -2.43, 73.18, 75.84, -2.66, 79.48, 86.07, -6.59, 71.33, 78.93, -7.59,
                            73.53, 78.85, -5.32],
                [49.20, 52.63, -3.43, 46.03, 51.87, -5.84, 48.23, 60.35, -12.12, 38.81, 53.23, -14.41,
                 42.95, 53.80, -10.85]),
    "ufld": ("UFLD", [65.90, 68.47, -2.57, 65.64, 67.58, -1.94, 67.73, 74.01, -6.27, 64.45, 70.88, -6.42,
                      65.45, 69.90, -4.44],
             [21.25, 24.54, -3.30, 28.23, 31.85, -3.62, 26.18, 36.32, -10.13, 19.96, 30.82, -10.85,
              23.57, 31.65, -8.08]),
    "bezierlanenet": ("BezierLaneNet", [73.14, 75.76, -2.62, 71.44, 74.51, -3.07, 68.79, 78.32, -9.54, 69.44, 75.31,
                                        -5.87, 70.00, 75.52, -5.52],
                      [37.84, 40.68, -2.85, 42.53, 50.03, -7.49, 41.41, 50.93, -9.52, 37.06, 45.86, -8.81,
                       39.49, 47.95, -8.46]),
    "ganet": ("GANet", [85.32, 89.33, -4.01, 80.53, 84.75, -4.22, 83.44, 93.02, -9.58, 79.21, 89.23, -10.02,
                        80.55, 88.08, -7.53],
              [79.01, 84.16, -5.15, 70.34, 80.79, -10.45, 73.50, 89.33, -15.83, 65.25, 83.03, -17.78,
               68.64, 83.25, -14.61]),
    "scnn": ("SCNN", [71.11, 71.94, -0.84, 67.17, 69.67, -2.50, 65.38, 70.33, -4.95, 63.88, 68.05, -4.16,
                      65.31, 69.36, -4.05],
             [48.69, 52.88, -4.19, 43.63, 50.47, -6.85, 34.92, 49.42, -14.50, 34.70, 46.94, -12.24,
              37.71, 49.19, -11.49]),
    "laneformer": ("LaneFormer", [87.14, 90.06, -2.92, 83.72, 87.25, -3.53, 86.20, 93.41, -7.21, 81.68, 89.20, -7.52,
                                  84.69, 89.98, -5.29],
                   [82.12, 86.57, -4.45, 74.65, 82.91, -8.26, 76.44, 90.24, -13.80, 69.52, 84.71, -15.19,
                    75.68, 86.11, -10.43]),
    "clrnet": ("CLRNet", [86.02, 88.77, -2.75, 82.63, 85.44, -2.81, 84.95, 91.22, -6.27, 80.37, 87.42, -7.05,
                          83.49, 88.21, -4.72],
               [80.93, 84.98, -4.05, 72.44, 80.36, -7.92, 74.35, 88.02, -13.67, 67.83, 82.25, -14.42,
                73.89, 83.40, -9.51]),
}
KINDS = ("Perturbed", "Original", "Gap")
# Families this project trains that the paper's table does not have: their rows show ours only.
NOT_IN_PAPER = {"clrernet": "CLRerNet"}


def published_row(family: str, score: str) -> dict:
    """The paper's values of one family and score as {'<category>/<kind>': value} (category 'average' too)."""
    name, accuracy, f1 = PUBLISHED[family]
    values = accuracy if score == "Accuracy" else f1
    keys = [f"{cat}/{kind}" for cat in (*CATEGORIES, "average") for kind in KINDS]
    return dict(zip(keys, values, strict=True))


def ours(row: dict, score: str) -> dict:
    return {f"{cat}/{kind}": row[f"{cat}/{score}/{kind}"] for cat in (*CATEGORIES, "average") for kind in KINDS}


def worst(values: dict) -> str:
    return min(CATEGORIES, key=lambda cat: values[f"{cat}/Gap"]).replace("_", " ")


def table(rows: list[dict]) -> str:
    head = ("| family | ours: Accuracy P / O / Gap | paper | ours: F1 P / O / Gap | paper | largest Accuracy Gap: "
            "ours | paper |\n|---|---|---|---|---|---|---|---|")
    lines = [head]
    for row in rows:
        family = row["model"].split("-")[0]
        if family not in PUBLISHED and family not in NOT_IN_PAPER:
            continue
        paper = family in PUBLISHED
        cells = [row["model"]]
        for score in ("Accuracy", "F1"):
            cells.append(" / ".join(f"{ours(row, score)[f'average/{k}']:.2f}" for k in KINDS))
            cells.append(" / ".join(f"{published_row(family, score)[f'average/{k}']:.2f}" for k in KINDS) if paper
                         else "not in the paper")
        cells += [worst(ours(row, "Accuracy")), worst(published_row(family, "Accuracy")) if paper else "—"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("report_dir", type=Path)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    path = next((p for p in (args.report_dir / "robustness" / "main.json", args.report_dir / "main.json")
                 if p.is_file()), None)
    if path is None:
        raise SystemExit(f"{args.report_dir}: no robustness/main.json or main.json (run task=report first)")
    text = table(json.loads(path.read_text()))
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
