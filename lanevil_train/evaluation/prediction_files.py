"""The official prediction files of an evaluation (``task.predictions=true``), written beside its scores.

Both go in the evaluation's ``predictions/`` folder:

- TuSimple: ``pred_tusimple.json``, JSON lines ``{"raw_file", "lanes", "h_samples", "run_time"}``: one line per
  image, each lane its x at every h_sample (-2 where the lane has no point), ``run_time`` in milliseconds per image (the
  network and its decoding, batched); what the TuSimple benchmark's ``LaneEval.bench_one_submit`` and
  ``python -m lanevil_train.metrics tusimple --pred predictions/pred_tusimple.json --gt test_label.json`` read.
- CULane: ``culane/<image path without extension>.lines.txt`` (one lane per line, "x y x y ...", the bottom
  point first) and ``culane/list.txt`` naming the images, what the CULane evaluation (``evaluate -a <gt root>
  -d predictions/culane/ -l predictions/culane/list.txt``) and ``python -m lanevil_train.metrics culane --pred-dir
  predictions/culane --gt-dir <root> --list predictions/culane/list.txt`` read.

The files are made from the per-image records at the end (``per_image.jsonl``, where streaming keeps every
image's predicted lanes at the network's own resolution when predictions are asked for), so a resumed
evaluation writes them whole, and each is replaced in one step: a run killed while writing leaves the old files
or none, never half of one.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path, PurePosixPath

import numpy as np

from lanevil_train.data.formats.culane import write_culane_lanes
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.lanes import culane_lanes, lanes_to_rows
from lanevil_train.results_log import ResultsLog

PREDICTIONS_DIR = "predictions"
TUSIMPLE_FILE = "pred_tusimple.json"
CULANE_DIR = "culane"
CULANE_LIST = "list.txt"
NO_POINT = -2  # TuSimple's x for a row a lane does not reach
CULANE_DECIMALS = 5  # as the official LaneATT and CLRNet writers ("{:.5f}"), trailing zeros dropped
FIELDS = ("pred_points", "h_samples", "run_time")
PREDICTION_FORMATS = ("tusimple", "culane")


def prediction_fields(pred: list[np.ndarray], meta: dict, run_time_ms: float, row_sampling: str = "linear",
                      culane_rows=None) -> dict:
    """What a per-image record keeps for the prediction files: the predicted lanes (original-image pixels, x and y
    to 1e-6 px: the spline writers truncate x, so a coarser point could move it across a whole pixel), how they are
    read at rows (the model's row sampling, lanes.ROW_SAMPLINGS, and CULane rows; named when not the default), the
    image's size and h_samples and the run time (ms)."""
    reading = {**({"row_sampling": row_sampling} if row_sampling != "linear" else {}),
               **({"culane_rows": list(culane_rows)} if culane_rows is not None else {})}
    return {"pred_points": [np.round(np.asarray(lane, dtype=np.float64), 6).tolist() for lane in pred],
            **({**reading, "height": int(meta["height"]), "width": int(meta["width"])} if reading else {}),
            "h_samples": [float(y) for y in meta["h_samples"]], "run_time": round(float(run_time_ms), 3)}


def tusimple_line(record: dict) -> dict:
    """One line of the TuSimple prediction file from a record holding ``prediction_fields``: each lane read at the
    h_samples as its row sampling says (x to 0.01 px; whole pixels where the sampling truncates, as the official
    spline writers)."""
    rows = np.asarray(record["h_samples"], dtype=np.float64)
    lanes = [np.asarray(points, dtype=np.float64).reshape(-1, 2) for points in record["pred_points"]]
    sampling = record.get("row_sampling", "linear")
    fewest = 1 if sampling == "points" else 2  # a row-wise writer writes a lane of one row (UFLD's), a line needs 2
    xs = lanes_to_rows([lane for lane in lanes if len(lane) >= fewest], rows, sampling, record.get("height"))
    number = int if sampling == "spline" else (lambda x: round(x, 2))
    return {"raw_file": record["key"],
            "lanes": [[number(float(x)) if x >= 0 else NO_POINT for x in lane] for lane in xs],
            "h_samples": [int(y) if float(y).is_integer() else y for y in record["h_samples"]],
            "run_time": record["run_time"]}


def _culane_relative(key: str) -> PurePosixPath:
    """The image's path under the predictions folder, without its extension; a key that would leave the folder is
    refused."""
    path = PurePosixPath(key.lstrip("/"))
    if not path.parts or ".." in path.parts:
        raise ValueError(f"image key {key!r} is not a relative path inside the dataset; cannot place its .lines.txt")
    return path.with_suffix("")


def write_prediction_files(results: str | Path, out_dir: str | Path,
                           formats: tuple[str, ...] = PREDICTION_FORMATS) -> dict[str, Path]:
    """Write ``predictions/pred_tusimple.json`` and/or the ``predictions/culane/`` tree (``formats``) in ``out_dir``
    from the records of ``results`` (per_image.jsonl written with predictions kept); returns {"tusimple": file,
    "culane": folder} of those written."""
    results = Path(results)
    records = ResultsLog(results).records()
    missing = [r["key"] for r in records if any(field not in r for field in FIELDS)]
    if missing:
        raise ValueError(f"{results}: {len(missing)} of {len(records)} images were scored without "
                         f"task.predictions=true (first: {missing[0]!r}), so their lanes were not kept; evaluate "
                         f"again into a new task.out_dir with task.predictions=true")
    return write_prediction_records(records, Path(out_dir) / PREDICTIONS_DIR, formats)


def write_prediction_records(records: list[dict], folder: str | Path,
                             formats: tuple[str, ...] = PREDICTION_FORMATS) -> dict[str, Path]:
    """The prediction files of ``formats`` (tusimple: ``folder/pred_tusimple.json``; culane: ``folder/culane/``
    with its list.txt) from records holding FIELDS, each written whole under a temporary name."""
    unknown = [name for name in formats if name not in PREDICTION_FORMATS]
    if unknown or not formats:
        raise ValueError(f"formats: expected some of {', '.join(PREDICTION_FORMATS)}, got {list(formats)}")
    folder = Path(folder)
    written = {}
    if "tusimple" in formats:
        written["tusimple"] = folder / TUSIMPLE_FILE
        atomic_write_text(written["tusimple"], "".join(json.dumps(tusimple_line(r)) + "\n" for r in records))
    if "culane" not in formats:
        return written
    culane = folder / CULANE_DIR
    partial = folder / f"{CULANE_DIR}.partial"
    shutil.rmtree(partial, ignore_errors=True)  # what a run killed here left
    names = []
    for record in records:
        relative = _culane_relative(record["key"])
        lanes = [np.asarray(points, dtype=np.float64).reshape(-1, 2) for points in record["pred_points"]]
        lanes = culane_lanes(lanes, record.get("culane_rows"), record.get("row_sampling", "linear"),
                             record.get("height"), record.get("width"))
        write_culane_lanes(lanes, partial / relative.with_suffix(".lines.txt"), decimals=CULANE_DECIMALS)
        names.append("/" + str(PurePosixPath(record["key"].lstrip("/"))))
    atomic_write_text(partial / CULANE_LIST, "".join(name + "\n" for name in names))
    shutil.rmtree(culane, ignore_errors=True)
    partial.rename(culane)
    written["culane"] = culane
    return written
