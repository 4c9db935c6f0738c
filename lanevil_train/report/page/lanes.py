"""report.html of a robustness run (task=evaluate / test / report): header, the tables of report.md and its plots,
seeds, and for lane detectors the gallery (for VLM runs the worst answers).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from lanevil_train.report.page.gallery import PER_TYPE, read_records, remove_stale_files, write_gallery
from lanevil_train.report.page.header import add_run_header, run_identities
from lanevil_train.report.page.html import Page
from lanevil_train.report.page.tables import add_plots, add_robustness_tables, add_seed_tables, robustness_plots
from lanevil_train.report.page.vlm import write_answers_section


# ---------------------------------------------------------------------------------------------- lane page
def write_robustness_page(out_dir: str | Path, result_files: Sequence[Path], rs=None,
                          labels: dict[Path, str] | None = None, per_type: int = PER_TYPE,
                          title: str = "Robustness report") -> Path:
    """report.html of a run whose report.md write_report (report/robustness.py) wrote in out_dir: header, its
    tables and plots, seeds (when task=report wrote seeds.json), and for lane detectors the gallery. `rs`: the
    run's record set when the caller has it (else the results files are read again, without lanes)."""
    from lanevil_train.report.specs import record_set

    out_dir = Path(out_dir)
    result_files = [Path(p) for p in result_files]
    labels = labels or {}
    if rs is None:
        records = [{**r, **({"model": labels[p]} if p in labels else {})} for p in result_files
                   for r in read_records(p, keep_lanes=False)]
        rs = record_set(records)
    page = Page(title)
    add_run_header(page, out_dir, run_identities(result_files, labels), rs.models)
    add_robustness_tables(page, out_dir, rs.spec)
    add_seed_tables(page, out_dir, rs.spec)
    add_plots(page, out_dir, robustness_plots(out_dir))
    keep: set[str] = set()
    if rs.spec.name == "lane" and any(r["severity"] > 0 for r in rs.records):
        body, keep = write_gallery(out_dir, rs, result_files, labels, per_type)
        if body:
            page.add_section("Gallery", body, "gallery")
    elif rs.spec.name == "vqa" and result_files:  # task=report over VLM runs: the first run's worst answers
        body, keep = write_answers_section(out_dir, result_files[0])
        if body:
            page.add_section("Worst answers", body, "answers")
    path = page.write(out_dir)
    remove_stale_files(out_dir, keep)
    return path
