"""task=leaderboard: rank robustness cards (robustness_card.json of task=evaluate or task=report) of one suite.

    python -m lanevil_train task=leaderboard task.cards=[a/robustness_card.json,b/robustness_card.json]
    python -m lanevil_train task=leaderboard task.cards=cards/ task.rank_by=Gap

The work is report/leaderboard.py's (plain Python); this writes leaderboard.md, .json and .html into the run folder
(task.out_dir) and returns the best model's value.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from lanevil_train.report.leaderboard import write_leaderboard
from lanevil_train.tasks.builders import output_dir


def leaderboard(cfg: DictConfig) -> float | None:
    """Rank task.cards by task.rank_by; the first row's value (None when no card has one)."""
    cards = cfg.task.cards
    cards = OmegaConf.to_container(cards, resolve=True) if OmegaConf.is_list(cards) else cards
    if not cards:
        raise ValueError("task=leaderboard needs task.cards=[a.json,b.json] (robustness cards) or a folder of cards")
    out = Path(cfg.task.out_dir) if cfg.task.get("out_dir") else output_dir(cfg)
    paths, rows = write_leaderboard(cards, out, cfg.task.get("rank_by"))
    print(f"Leaderboard of {len(rows)} cards: {paths['html']} (also {paths['md'].name}, {paths['json'].name})")
    return rows[0]["value"] if rows else None
