"""The VLM defense compare over several seeds: each defense's gain over `none` (mean, sample std and the seeds'
values) per illusion category and on average, for every score the compares hold, from the defense_gain.json files
that `task=compare` wrote, one per seed; and each run's wall time from its results files.

    python benchmarks/vlm_defense_seeds.py /work/bench/cmp_s0 /work/bench/cmp_s1 /work/bench/cmp_s2 \
        [--plot docs/vlm_defense_seeds.png]

The compares must share their suite (they differ by `seed=` only); a defense that some of them lack (a compare
stopped early, or run over fewer defenses) is summarised over the seeds that hold it, with their number shown.
A mean gain whose interval mean +- 2 std / sqrt(n) holds 0 is marked "~" (not told apart from zero by these
seeds). This predates `task.seeds`: `task=compare task.seeds=[0,1,2]` (or `task.runs=[cmp_s0,cmp_s1,cmp_s2]`, whose
runs differ by seed) now gives the same means with a paired bootstrap interval over test cases and seeds.
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


def mean_std(values: list[float]) -> tuple[float, float]:
    """The mean and the sample std (NaN for one value)."""
    n = len(values)
    mean = sum(values) / n
    return mean, math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else float("nan")


def summary(values: list[float], seeds: int) -> str:
    """mean +- sample std, marked ~ when mean +- 2 std/sqrt(n) holds zero, and (n=k) when only k of the seeds
    hold the value."""
    n = len(values)
    mean, std = mean_std(values)
    unclear = n < 2 or abs(mean) <= max(2 * std / math.sqrt(n), 0.005)  # 0.005: below the shown precision
    return f"{mean:+.2f} ± {std:.2f}{' ~' if unclear else ''}{f' (n={n})' if n < seeds else ''}"


def run_minutes(run: Path) -> float:
    """A compare run's wall time: its first file's modification to its last (checkpoints, prefix, test)."""
    times = [p.stat().st_mtime for p in run.rglob("*") if p.is_file()]
    return (max(times) - min(times)) / 60 if times else float("nan")


def plot_average_gains(table: dict[tuple[str, str, str], list[float]], scores: list[str], path: Path) -> None:
    """One panel per score: each defense's average gain over none, the bar its mean over the seeds, the whisker
    its std, the dots the seeds themselves."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    defenses = list(dict.fromkeys(d for d, c, _ in table if c == "average"))
    fig, axes = plt.subplots(1, len(scores), figsize=(1.5 + 0.4 * len(defenses) * len(scores), 3.6), squeeze=False)
    for ax, score in zip(axes[0], scores):
        for i, defense in enumerate(defenses):
            values = table.get((defense, "average", score), [])
            if not values:
                continue
            mean, std = mean_std(values)
            ax.bar(i, mean, 0.7, yerr=0.0 if math.isnan(std) else std, capsize=3, color=f"C{i}", alpha=0.8)
            ax.scatter([i] * len(values), values, s=10, color="black", zorder=3)
        ax.axhline(0.0, color="black", linewidth=0.8)
        ax.set_xticks(range(len(defenses)), defenses, rotation=45, ha="right", fontsize=8)
        ax.set_ylabel("gain over none (points)")
        ax.set_title(f"average perturbed {score}", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"\nwrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("compares", nargs="+", type=Path, help="task=compare output folders, one per seed")
    parser.add_argument("--plot", type=Path, help="draw the average gains (mean, std, seeds) per score here")
    args = parser.parse_args()
    table = gains_by_seed(args.compares)
    scores = list(dict.fromkeys(score for _, _, score in table))
    categories = list(dict.fromkeys(category for _, category, _ in table))
    for score in scores:
        print(f"\n### {score}: gain over none (points), mean ± std over {len(args.compares)} seeds\n")
        print("| defense | " + " | ".join(categories) + " |")
        print("|---" * (len(categories) + 1) + "|")
        for defense in dict.fromkeys(d for d, _, _ in table):
            cells = [summary(table[(defense, c, score)], len(args.compares)) if (defense, c, score) in table else ""
                     for c in categories]
            print(f"| {defense} | " + " | ".join(cells) + " |")
    print("\n### Run wall time (minutes, per seed)\n")
    runs = sorted({p.name for compare in args.compares for p in (compare / "runs").iterdir()})
    for name in runs:
        print(f"- {name}: " + ", ".join(f"{run_minutes(c / 'runs' / name):.1f}" for c in args.compares
                                        if (c / "runs" / name).is_dir()))
    if args.plot:
        plot_average_gains(table, scores, args.plot)


if __name__ == "__main__":
    main()
