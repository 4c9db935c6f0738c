"""report.html: one self-contained page per run, beside report.md, made from the run's record and table files.

What the page holds (each from files the run already wrote, never from a model):

- a header: the model(s), each one's weights sha256 and checkpoint, the command line, the package version and the
  date the page was written (header.py);
- the tables of report.md, from the same rows (main.json, per_type.json, ... as report/robustness.py wrote them),
  grouped, sortable, each Gap coloured by its sign and size, intervals and mean ± std under the values (html.py,
  tables.py);
- the run's PNG plots (score vs severity, the type x severity heatmap, gain bars), as <img> with paths relative to
  the page (tables.py);
- for lane detectors, a gallery per illusion type: the images that illusion hurt most, drawn clean | perturbed with
  the true and the predicted lanes, written as small JPEGs into report_files/ beside the page (gallery.py).

The same builder makes the other runs' pages, each with its own sections: write_robustness_page (a robustness run's,
lanes.py), write_vlm_page (a VLM's evaluation or test: its tables, the Gap intervals, visual reliance, DriveLM and
language tables, and the worst answers beside frames of the clean and the perturbed clip, read from the clip files or
rendered again from per_answer.suite.json; vlm.py), write_compare_page (task=compare: gains over `none` with their
intervals, scores per defense, links to each run's page; compare.py) and write_closed_loop_page (task=closed_loop:
ASR with Wilson intervals, collisions, time to collision and departure, the ASR and deviation plots, worst_run.gif;
closed_loop.py).

The page needs nothing from elsewhere: no CDN, font, script or style is fetched (the script and style are inline)
and it opens from disk with no server. It is written atomically, so a resumed run rewrites it whole, and the JPEGs
of report_files/ that the new page no longer shows are removed.

The parts: html.py (cells, columns, tables, Page, plots: the page-building primitives), header.py (the header),
tables.py (report.md's tables, seeds, plots as sections), gallery.py (the lane gallery and its images), lanes.py,
vlm.py, compare.py and closed_loop.py (one page each). This package re-exports their public names.
"""

from __future__ import annotations

from lanevil_train.report.page.closed_loop import CLOSED_LOOP_INTERVALS, fold_text_intervals, write_closed_loop_page
from lanevil_train.report.page.compare import write_compare_page
from lanevil_train.report.page.gallery import (
    IMAGE_WIDTH,
    JPEG_QUALITY,
    LANE_FIELDS,
    PER_TYPE,
    SUITE_FILE_SUFFIX,
    ImageSource,
    Pick,
    draw_lanes,
    gallery_picks,
    read_records,
    remove_stale_files,
    suite_file,
    write_gallery,
    write_jpeg,
)
from lanevil_train.report.page.header import add_run_header, command_line, run_identities
from lanevil_train.report.page.html import (
    CSS,
    FILES,
    GAP_LABELS,
    GAP_LEGEND,
    PAGE,
    SCRIPT,
    Cell,
    Column,
    Page,
    columns_of,
    esc,
    perturbed_named,
    plots_html,
    slug,
    table_html,
)
from lanevil_train.report.page.lanes import write_robustness_page
from lanevil_train.report.page.tables import (
    LATER_TABLES,
    TABLES,
    add_plots,
    add_robustness_tables,
    add_seed_tables,
    main_long_cells,
    robustness_plots,
)
from lanevil_train.report.page.vlm import (
    ANSWER_FIELDS,
    FRAME_WIDTH,
    STRIP_FRAMES,
    VLM_TABLES,
    FrameSource,
    fold_intervals,
    worst_answer_pairs,
    write_answers_section,
    write_vlm_page,
)

__all__ = [
    "ANSWER_FIELDS", "CLOSED_LOOP_INTERVALS", "CSS", "FILES", "FRAME_WIDTH", "GAP_LABELS", "GAP_LEGEND", "IMAGE_WIDTH",
    "JPEG_QUALITY", "LANE_FIELDS", "LATER_TABLES", "PAGE", "PER_TYPE", "SCRIPT", "STRIP_FRAMES", "SUITE_FILE_SUFFIX",
    "TABLES", "VLM_TABLES", "Cell", "Column", "FrameSource", "ImageSource", "Page", "Pick", "add_plots",
    "add_robustness_tables", "add_run_header", "add_seed_tables", "columns_of", "command_line", "draw_lanes", "esc",
    "fold_intervals", "fold_text_intervals", "gallery_picks", "main_long_cells", "perturbed_named", "plots_html",
    "read_records", "remove_stale_files", "robustness_plots", "run_identities", "slug", "suite_file", "table_html",
    "worst_answer_pairs", "write_answers_section", "write_closed_loop_page", "write_compare_page", "write_gallery",
    "write_jpeg", "write_robustness_page", "write_vlm_page",
]
