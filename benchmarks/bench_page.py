"""What report.html costs: the time to build the page (tables, plots shown, the gallery's images rendered again and
drawn) beside the time write_report takes for report.md, and the size of the page and its report_files/.

Reads a finished run's per_image.jsonl (e.g. a quickstart's robustness/per_image.jsonl) into a scratch folder,
never writing beside it. A results file of an on-the-fly suite needs its per_image.suite.json beside it to render
the gallery; give --suite to write one for a run made before evaluations wrote it (the quickstart's:
--suite 10 1000000 720 1280).

Usage: python benchmarks/bench_page.py RUN/robustness/per_image.jsonl [--suite CASES FIRST_SEED H W] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path)
    parser.add_argument("--suite", type=int, nargs=4, metavar=("CASES", "FIRST_SEED", "H", "W"))
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    from lanevil_train.data.suites import SyntheticIllusionSuite
    from lanevil_train.evaluation.lane_records import read_records
    from lanevil_train.report.page import FILES, PAGE, suite_file, write_robustness_page
    from lanevil_train.report.robustness import write_report
    from lanevil_train.report.specs import record_set

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        results = out / "per_image.jsonl"
        shutil.copy(args.results, results)
        for extra in (args.results.with_name(f"{args.results.stem}.run.json"), suite_file(args.results)):
            if extra.is_file():
                shutil.copy(extra, out / extra.name)
        if args.suite:
            cases, first_seed, h, w = args.suite
            suite_file(results).write_text(json.dumps(SyntheticIllusionSuite(cases, first_seed, (h, w)).description()))
        rs = record_set(read_records(results, keep_lanes=False))
        report, page = [], []
        for _ in range(args.repeat):
            start = time.perf_counter()
            write_report(rs, out)
            report.append(time.perf_counter() - start)
            start = time.perf_counter()
            write_robustness_page(out, [results], rs)
            page.append(time.perf_counter() - start)
        files = list((out / FILES).glob("*.jpg"))
        print(json.dumps({"records": len(rs.records), "report_md_s": [round(t, 2) for t in report],
                          "page_s": [round(t, 2) for t in page],
                          "page_kb": round((out / PAGE).stat().st_size / 1024, 1), "report_files": len(files),
                          "report_files_kb": round(sum(p.stat().st_size for p in files) / 1024, 1)}, indent=1))


if __name__ == "__main__":
    main()
