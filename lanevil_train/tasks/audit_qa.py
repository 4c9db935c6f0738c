"""task=audit_qa: how much of a QA file's closed answers the words alone give away (vlm/answer_scoring/leakage.py).

    python -m lanevil_train task=audit_qa task.suite=PATH   # a clip suite folder or a DriveLM-style QA .json
    python -m lanevil_train task=audit_qa task.suite=synthetic task.cases=200   # this benchmark's own QA

Writes qa_audit.{json,md,png} in task.out_dir (default: the run directory) and prints the per-type rows and the
templates that leak; returns the yes/no text-only accuracy (%), the number a benchmark wants near 50.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from lanevil_train.errors import prefixed
from lanevil_train.report.tables import print_table
from lanevil_train.tasks.builders import output_dir
from lanevil_train.vlm.answer_scoring.leakage import audit, read_qa_file, synthetic_qa, write_audit


def audit_qa(cfg: DictConfig) -> float:
    task = cfg.task
    try:
        records = (synthetic_qa(task.cases, task.first_seed, cfg.progress) if task.suite == "synthetic"
                   else read_qa_file(task.suite))
    except (FileNotFoundError, ValueError) as error:
        raise prefixed(error, f"task.suite={task.suite}") from None
    out = Path(task.out_dir) if task.out_dir else output_dir(cfg)
    result = audit(records, folds=task.folds, seed=cfg.seed, min_count=task.min_count, alpha=task.alpha)
    paths = write_audit(result, out, str(task.suite))
    print_table(result["by_type"], title=f"Text-only reader on held-out scenes (%) — {paths['md']}")
    leaking = result["leaking"]
    print(f"{len(leaking)} of {result['settings']['templates_judged']} templates judged give their answer away"
          + "".join(f"\n  {t['type']}: {t['template']!r} (n {t['n']})" for t in leaking[:10])
          + ("\n  ..." if len(leaking) > 10 else ""))
    yes_no = [r for r in result["by_type"] if r["type"] == "yes_no"]
    return float(yes_no[0]["text_only_accuracy"]) if yes_no else float(result["by_type"][0]["text_only_accuracy"])
