"""The VLM defense compare over several seeds: each defense's gain over `none` (mean, sample std and the seeds'
values) per illusion category and on average, for every score the compares hold, from the defense_gain.json files
that `task=compare` wrote, one per seed; and each run's wall time from its results files.

    python benchmarks/vlm_defense_seeds.py /work/bench/cmp_s0 /work/bench/cmp_s1 /work/bench/cmp_s2

The compares must share their suite (they differ by `seed=` only); a defense that some of them lack (a compare
stopped early, or run over fewer defenses) is summarised over the seeds that hold it, with their number shown.
A mean gain whose interval mean +- 2 std / sqrt(n) holds 0 is marked "~" (not told apart from zero by these
seeds; a paired bootstrap over test cases is issue 17's).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def gains_by_seed(compares: list[Path]) -> dict[tuple[str, str, str], list[float]]:
    """(defense, category, score) -> the gain in each compare, in the order given."""
    table: dict[tuple[str, str, str], list[float]] = {}
    for compare in compares:
        for row in json.loads((compare / "defense_gain.json").read_text()):
            for key, value in row.items():
                if key.endswith("/gain"):
                    table.setdefault((row["defense"], row["category"], key[:-5]), []).append(float(value))
    return table


def summary(values: list[float], seeds: int) -> str:
    """mean +- sample std, marked ~ when mean +- 2 std/sqrt(n) holds zero, and (n=k) when only k of the seeds
    hold the value."""
    n = len(values)
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else float("nan")
    unclear = n < 2 or abs(mean) <= max(2 * std / math.sqrt(n), 0.005)  # 0.005: below the shown precision
    return f"{mean:+.2f} ± {std:.2f}{' ~' if unclear else ''}{f' (n={n})' if n < seeds else ''}"


def run_minutes(run: Path) -> float:
    """A compare run's wall time: its first file's modification to its last (checkpoints, prefix, test)."""
    times = [p.stat().st_mtime for p in run.rglob("*") if p.is_file()]
    return (max(times) - min(times)) / 60 if times else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("compares", nargs="+", type=Path, help="task=compare output folders, one per seed")
    args = parser.parse_args()
    table = gains_by_seed(args.compares)
    scores = list(dict.fromkeys(score for _, _, score in table))
    categories = list(dict.fromkeys(category for _, category, _ in table))
    for score in scores:
        print(f"\n### {score}: gain over none (points), mean ± std over {len(args.compares)} seeds\n")
        print("| defense | " + " | ".join(categories) + " |")
        print("|---" * (len(categories) + 1) + "|")
        for defense in dict.fromkeys(d for d, _, _ in table):
            cells = [summary(table[(defense, c, score)], len(args.compares)) if (defense, c, score) in table else "" for c in categories]
            print(f"| {defense} | " + " | ".join(cells) + " |")
    print("\n### Run wall time (minutes, per seed)\n")
    runs = sorted({p.name for compare in args.compares for p in (compare / "runs").iterdir()})
    for name in runs:
        print(f"- {name}: " + ", ".join(f"{run_minutes(c / 'runs' / name):.1f}" for c in args.compares
                                        if (c / "runs" / name).is_dir()))


if __name__ == "__main__":
    main()
