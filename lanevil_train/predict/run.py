"""A detector over a frame source (sources.py), writing what task=predict writes, in plain Python:

- ``frames/<key>.jpg``: every frame with its lanes drawn (drawing.py); an image's key is its path relative to the
  input folder (its extension replaced by .jpg), a video frame's ``frame_%06d`` (its index in the video); not with
  ``write_frames=False`` (a long video's JPEGs take far more room than its annotated video);
- ``<video stem>_lanes.mp4`` for a video: the drawn frames at the video's size and frame rate (divided by the
  stride, so that it plays at the source's speed), MPEG-4 (``mp4v``: what OpenCV's own FFmpeg writes everywhere),
  written under a temporary name and renamed when whole;
- ``per_frame.jsonl`` (results_log.ResultsLog): one line per frame: ``key`` (``frame``: a video frame's index),
  ``height``, ``width``, ``pred_points`` (the lanes' points in the frame's pixels), ``scores`` (the family's
  confidence of each lane), ``h_samples`` (the TuSimple rows at the frame's height) and ``run_time`` (ms per frame:
  the network and its decoding, batched), appended once the frame's drawn image is on disk;
- ``predictions/pred_tusimple.json`` (TuSimple JSON lines) and/or ``predictions/culane/`` (CULane .lines.txt and
  list.txt), made from per_frame.jsonl at the end by evaluation/prediction_files.py's writers;
- ``summary.json``: the counts, the unreadable frames, the throughput (``frames_per_s``: frames predicted in this
  run over the loop's wall time, reading to the last write; the model's loading not included) and where the time
  went (``timing``: ``predict_s`` the network and decoding, in the calling thread; ``write_s`` drawing, JPEG and video
  encoding and per_frame.jsonl, in the writing thread; ``wait_read_s`` / ``wait_write_s`` the calling thread waiting
  for frames / for the writer; ``cpu_s`` every thread's CPU time).

With ``PredictSettings.illusion`` (task.illusion=NAME, predict/illusion.py) every frame is predicted twice, clean and
with the illusion on the ground its lanes give: the drawn frames and the video are clean | illusion side by side
(twice the width), a frame's line gains ``illusion``: the illusion's lanes (``pred_points``, ``scores``, ...), its
``layout`` (a video's 0, 1, ...), where its ground came from (``ground``: prediction or labels) and how it changed
the lanes (``kept``, ``lost``, ``added``, ``accuracy``: predict.illusion.lane_changes), or ``passed_through`` (why no
ground plane) for a frame drawn clean on both sides; ``predictions/illusion/`` holds the illusion's prediction files
and summary.json its totals.

A rerun into the same folder resumes: an image already in per_frame.jsonl is not read again; a video is decoded
again from its start (frames are read in order), its finished frames redrawn from their lines without the network
and the annotated video written whole again (an interrupted run leaves no half video: its temporary is removed at
the next start). Resuming another model's or another input's results is refused (evaluation/streaming.py's run
identity, in per_frame.run.json).

The lanes are LaneDetector.predict's, done in three threads: frames are read and preprocessed ahead in one
(the detector's own Preprocessor), the network and its decoding (decode_lanes, with scores) run on a batch in the
calling thread, and the previous batch is drawn and written in a third.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from lanevil_train.evaluation.prediction_files import PREDICTIONS_DIR, prediction_fields, write_prediction_records
from lanevil_train.evaluation.streaming import claim_results, run_identity
from lanevil_train.files.atomic import atomic_write_bytes, atomic_write_text
from lanevil_train.lanes import default_h_samples
from lanevil_train.predict.drawing import draw_lanes
from lanevil_train.predict.illusion import IllusionSettings, RoadIllusion, lane_changes, side_by_side
from lanevil_train.predict.sources import FrameSource
from lanevil_train.progress import MODES, progress_counter
from lanevil_train.results_log import ResultsLog
from lanevil_train.rules import boolean, check_settings, integer, one_of

log = logging.getLogger(__name__)

FORMATS = {"tusimple": ("tusimple",), "culane": ("culane",), "both": ("tusimple", "culane")}
ILLUSION_DIR = "illusion"  # predictions/illusion/: the prediction files of the frames with the illusion
RESULTS_FILE = "per_frame.jsonl"
SUMMARY_FILE = "summary.json"
FRAMES_DIR = "frames"
VIDEO_SUFFIX = "_lanes.mp4"
VIDEO_CODEC = "mp4v"
LISTED_UNREADABLE = 20  # the unreadable frames named in the final line (all are in summary.json)


@dataclass(frozen=True)
class PredictSettings:
    """How predict_source runs: frames per network call, which official prediction files it writes (tusimple,
    culane or both), the progress display (progress.MODES), whether the drawn frames go to frames/ (False: a
    video's only in the annotated video, an image's nowhere) and their JPEG quality."""

    batch_size: int = 8
    format: str = "both"
    progress: str = "auto"
    write_frames: bool = True
    jpeg_quality: int = 95
    illusion: IllusionSettings | None = None

    SETTINGS = {"batch_size": integer(1), "format": one_of(*FORMATS), "progress": one_of(*MODES),
                "write_frames": boolean(), "jpeg_quality": integer(1, 100)}

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, vars(self), "")


@dataclass
class _Frame:
    key: str
    image: np.ndarray
    input: np.ndarray | None  # the network's input (3xHxW float32) of a frame to predict
    record: dict | None  # None until predicted
    new: bool
    perturbed: np.ndarray | None = None  # with task.illusion: the frame with the illusion (None: passed through)


def frame_record(key: str, image: np.ndarray, lanes: list, run_time_ms: float, detector) -> dict:
    """The per_frame.jsonl line of a frame and its PredictedLanes (module docstring)."""
    height, width = (int(v) for v in image.shape[:2])
    meta = {"height": height, "width": width, "h_samples": default_h_samples(height)}
    fields = prediction_fields([lane.points for lane in lanes], meta, run_time_ms,
                               getattr(detector, "row_sampling", "linear"), getattr(detector, "culane_rows", None))
    frame = {"frame": int(key.rsplit("_", 1)[1])} if key.startswith("frame_") and key[6:].isdigit() else {}
    return {"key": key, **frame, "height": height, "width": width, **fields,
            "scores": [round(float(lane.score), 6) for lane in lanes]}


def record_lanes(record: dict) -> list[tuple[np.ndarray, float]]:
    """(points, score) of each lane of a per_frame.jsonl line."""
    return [(np.asarray(points, dtype=np.float64).reshape(-1, 2), float(score))
            for points, score in zip(record["pred_points"], record["scores"])]


class _VideoOut:
    """The annotated video: opened at its first frame, written to a hidden temporary beside its final name (ending
    in .mp4, which OpenCV needs to pick the container) and renamed over it by close()."""

    def __init__(self, path: Path, fps: float):
        self.path, self.fps = path, fps
        self.tmp = path.with_name(f".{path.name}.{os.getpid()}.{os.urandom(4).hex()}.partial.mp4")
        self.writer = None
        self.size: tuple[int, int] | None = None
        self.count = 0
        for stale in path.parent.glob(f".{path.name}.*.partial.mp4"):  # what a killed run left
            stale.unlink(missing_ok=True)

    def write(self, image: np.ndarray) -> None:
        if self.writer is None:
            self.size = (int(image.shape[1]), int(image.shape[0]))
            self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*VIDEO_CODEC), self.fps, self.size)
            if not self.writer.isOpened():
                raise RuntimeError(f"{self.path}: OpenCV cannot write an {VIDEO_CODEC} video here")
        if (image.shape[1], image.shape[0]) != self.size:  # a frame of another size (rare in a video)
            image = cv2.resize(image, self.size, interpolation=cv2.INTER_AREA)
        self.writer.write(image)
        self.count += 1

    def close(self) -> Path | None:
        """Finish the file and give it its name (None when no frame was written)."""
        if self.writer is None:
            return None
        self.writer.release()
        self.writer = None
        with open(self.tmp, "rb") as handle:
            os.fsync(handle.fileno())
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        if self.writer is not None:
            self.writer.release()
            self.writer = None
        self.tmp.unlink(missing_ok=True)


def _read_ahead(frames, depth: int):
    """The items of the iterator `frames`, read in a background thread up to `depth` ahead (OpenCV's decoding runs
    while the network does); the thread stops, and closes `frames`, when the consumer stops."""
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    end = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                items.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work() -> None:
        try:
            for item in frames:
                if not put(item):
                    break
            put((end, None))
        except BaseException as error:  # noqa: BLE001 - handed to the consumer, raised there
            put((end, error))
        finally:
            close = getattr(frames, "close", None)
            if close is not None:
                close()

    thread = threading.Thread(target=work, name="predict-read", daemon=True)
    thread.start()
    waited = 0.0
    try:
        while True:
            start = time.perf_counter()
            item = items.get()
            waited += time.perf_counter() - start
            if isinstance(item, tuple) and item and item[0] is end:
                if item[1] is not None:
                    raise item[1]
                return
            yield item, waited
    finally:
        stop.set()
        thread.join(timeout=10)


def _prepared(frames, preprocessor, previous: dict):
    """(key, image, the network's input) of each frame, the input None for a frame whose record is in `previous`
    (a finished frame of a resumed video, redrawn); run in the reading thread."""
    try:
        for key, image in frames:
            yield key, image, None if key in previous else preprocessor.image(image, "bgr")
    finally:
        frames.close()


def predict_source(detector, source: FrameSource, out_dir: str | Path, settings: PredictSettings | None = None,
                   labels: dict[str, list[np.ndarray]] | None = None) -> dict:
    """Run `detector` (a LaneDetector, in eval mode on its device) over `source`, writing into `out_dir` what the
    module docstring lists; returns the summary (also in summary.json). With ``settings.illusion`` each frame is
    predicted clean and with the illusion (predict/illusion.py), its ground from `labels` (the lanes of a frame's
    key, in its pixels) where they have the frame, else from the clean prediction."""
    settings = settings or PredictSettings()
    labels = labels or {}
    illusion = settings.illusion
    road = None if illusion is None else (RoadIllusion.for_video(illusion, source.fps) if source.is_video
                                          else RoadIllusion(illusion))
    detector.eval()
    preprocessor = detector.preprocessor
    device = next(detector.parameters()).device
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = ResultsLog(out / RESULTS_FILE)
    done = results.resume()
    identity = {"input": str(source.path.resolve()), "stride": source.stride,
                **({} if illusion is None else {**illusion.identity(), "labels": sorted(labels)})}
    claim_results(results.path, run_identity(detector, identity), resuming=bool(done))
    previous = {record["key"]: record for record in results.records()} if source.is_video and done else {}
    video = _VideoOut(out / f"{source.path.stem}{VIDEO_SUFFIX}", source.fps / source.stride) \
        if source.is_video else None
    frames_dir = out / FRAMES_DIR
    timing = {"predict_s": 0.0, "write_s": 0.0, "wait_read_s": 0.0, "wait_write_s": 0.0,
              **({} if illusion is None else {"illusion_s": 0.0})}
    initial = 0 if source.is_video else sum(key in done for key in source.keys)
    bar = progress_counter(source.total if source.total is not None else float("inf"), initial, "predict", "frame",
                           settings.progress)
    counts = {"predicted": 0, "redrawn": 0}
    illusion_label = None if illusion is None else f"{illusion.name}, severity {illusion.severity}"

    def drawn_frame(frame: _Frame) -> np.ndarray:
        if illusion is None:
            return draw_lanes(frame.image, record_lanes(frame.record), copy=False)  # the frame is not used again
        perturbed = frame.record["illusion"]
        right = draw_lanes(frame.perturbed, record_lanes(perturbed), copy=False) if frame.perturbed is not None \
            else frame.image.copy()
        title = f"{illusion_label}: {perturbed['lost']} lost, {perturbed['added']} added" \
            if frame.perturbed is not None else "passed through: no ground plane"
        return side_by_side(draw_lanes(frame.image, record_lanes(frame.record), copy=False), right, "clean", title)

    def write(batch: list[_Frame]) -> None:  # in the writer thread, one batch at a time, in order
        start = time.perf_counter()
        for frame in batch:
            path = frames_dir / source.frame_name(frame.key)
            jpeg = settings.write_frames and (frame.new or not path.is_file())
            if not jpeg and video is None:
                continue
            drawn = drawn_frame(frame)
            if jpeg:
                ok, data = cv2.imencode(".jpg", drawn, [cv2.IMWRITE_JPEG_QUALITY, settings.jpeg_quality])
                if not ok:
                    raise RuntimeError(f"{path}: OpenCV could not encode the drawn frame as JPEG")
                atomic_write_bytes(path, data.tobytes())
            if video is not None:
                video.write(drawn)
        new = [frame.record for frame in batch if frame.new]
        if new:
            results.append(new)  # after their drawn frames: a line in the file means its frame is on disk
        timing["write_s"] += time.perf_counter() - start

    def predict_batch(inputs: list[np.ndarray], frames: list[_Frame], image: str) -> list[dict]:
        """LaneDetector.predict on the network inputs of `frames` (their `image` attribute: the frame or its
        perturbed twin): each one's per_frame record, the batch's time shared out."""
        start = time.perf_counter()
        with torch.inference_mode():
            predicted = detector.decode_lanes(detector(torch.from_numpy(np.stack(inputs)).to(device)),
                                              preprocessor.input_size, [frame.image.shape[:2] for frame in frames],
                                              with_scores=True)
        elapsed = time.perf_counter() - start
        timing["predict_s"] += elapsed
        return [frame_record(frame.key, getattr(frame, image), lanes, elapsed * 1000 / len(frames), detector)
                for frame, lanes in zip(frames, predicted)]

    def with_illusion(new: list[_Frame]) -> None:
        """Every pending frame in order with the illusion on its ground; a new one's lanes predicted on it."""
        start = time.perf_counter()
        for frame in pending:
            key = os.path.normpath(frame.key)
            lanes = labels[key] if key in labels else [points for points, _ in record_lanes(frame.record)]
            drawn = road.apply(frame.image, lanes, frame.record.get("frame"))
            frame.perturbed = drawn.image
            if frame.new:
                frame.record["illusion"] = {"passed_through": drawn.passed_through} if drawn.image is None else \
                    {"layout": drawn.layout, "ground": "labels" if key in labels else "prediction"}
        timing["illusion_s"] += time.perf_counter() - start
        drawn = [frame for frame in new if frame.perturbed is not None]
        if not drawn:
            return
        inputs = [preprocessor.image(frame.perturbed, "bgr") for frame in drawn]
        for frame, lanes_record in zip(drawn, predict_batch(inputs, drawn, "perturbed")):
            height, width = frame.image.shape[:2]
            changes = lane_changes([points for points, _ in record_lanes(frame.record)],
                                   [points for points, _ in record_lanes(lanes_record)], height, width)
            frame.record["illusion"].update({name: lanes_record[name] for name in lanes_record
                                             if name not in ("key", "frame", "height", "width")}, **changes)

    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="predict-write")
    writing: Future | None = None
    pending: list[_Frame] = []

    def flush() -> None:
        nonlocal writing
        new = [frame for frame in pending if frame.record is None]
        if new:  # their preprocessing done in the reading thread
            for frame, record in zip(new, predict_batch([frame.input for frame in new], new, "image")):
                frame.record, frame.input = record, None
            counts["predicted"] += len(new)
        if road is not None:
            with_illusion(new)
        counts["redrawn"] += len(pending) - len(new)
        if writing is not None:
            start = time.perf_counter()
            writing.result()  # the previous batch is written (its error, if any, raised here)
            timing["wait_write_s"] += time.perf_counter() - start
        writing = pool.submit(write, list(pending))
        bar.update(len(pending))
        pending.clear()

    start, cpu = time.perf_counter(), time.process_time()
    try:
        frames = _prepared(source.frames(skip=() if source.is_video else done), preprocessor, previous)
        for (key, image, inputs), waited in _read_ahead(frames, 2 * settings.batch_size):
            timing["wait_read_s"] = waited
            record = previous.get(key)
            pending.append(_Frame(key, image, inputs, record, new=record is None))
            if sum(frame.new for frame in pending) >= settings.batch_size or len(pending) >= 4 * settings.batch_size:
                flush()
        if pending:
            flush()
        if writing is not None:
            writing.result()
        unread = source.selected - initial - counts["predicted"] - counts["redrawn"]
        if unread > 0:
            bar.update(unread)  # the unreadable frames, counted as gone through
        video_path = video.close() if video is not None else None
    except BaseException:
        pool.shutdown(wait=True)  # the writer done with the video before its temporary goes
        if video is not None:
            video.abort()
        raise
    finally:
        pool.shutdown(wait=True)
        bar.close()
    elapsed = time.perf_counter() - start
    timing["cpu_s"] = time.process_time() - cpu  # every thread's CPU time over the loop (on a shared machine, steadier)

    records = results.records() if results.path.exists() else []
    if not records:
        raise ValueError(f"{source.path}: none of its {source.selected} selected frames could be read "
                         f"({', '.join(source.unreadable[:LISTED_UNREADABLE])})")
    predictions = write_prediction_records(records, out / PREDICTIONS_DIR, FORMATS[settings.format])
    if illusion is not None:
        perturbed = [{**record, **record["illusion"]} for record in records if "pred_points" in record["illusion"]]
        if perturbed:
            written = write_prediction_records(perturbed, out / PREDICTIONS_DIR / ILLUSION_DIR,
                                               FORMATS[settings.format])
            predictions.update({f"illusion_{name}": path for name, path in written.items()})
    if source.unreadable:
        names = source.unreadable[:LISTED_UNREADABLE]
        more = len(source.unreadable) - len(names)
        log.warning("%d of %d frames unreadable, skipped: %s%s", len(source.unreadable), source.selected,
                    ", ".join(names), f", ... and {more} more (all in {out / SUMMARY_FILE})" if more else "")
    summary = {"input": str(source.path), "kind": source.kind, "selected": source.selected,
               "predicted": counts["predicted"], "already_done": len(done), "redrawn": counts["redrawn"],
               "unreadable": list(source.unreadable), "records": len(records),
               "seconds": round(elapsed, 3),
               "frames_per_s": round(counts["predicted"] / elapsed, 3) if counts["predicted"] and elapsed > 0 else 0.0,
               "timing": {name: round(value, 3) for name, value in timing.items()},
               "frames": str(frames_dir) if settings.write_frames else None,
               "video": str(video_path) if video_path else None,
               "video_fps": video.fps if video is not None else None, "per_frame": str(results.path),
               "predictions": {name: str(path) for name, path in predictions.items()},
               **({} if illusion is None else {"illusion": illusion_summary(records, illusion)})}
    atomic_write_text(out / SUMMARY_FILE, json.dumps(summary, indent=1) + "\n")
    written = [frames_dir if settings.write_frames else None, video_path, results.path, *predictions.values()]
    log.info("task=predict: %d frames predicted (%d already done%s) in %.1f s (%.2f frames/s); wrote %s",
             counts["predicted"], len(done), f", {counts['redrawn']} redrawn" if counts["redrawn"] else "", elapsed,
             summary["frames_per_s"], ", ".join(str(path) for path in written if path is not None))
    return summary


def illusion_summary(records: list[dict], illusion: IllusionSettings) -> dict:
    """The illusion's effect over a run's frames: how many carried it, how many were passed through (no ground
    plane), the clean lanes lost and the lanes added under it, and the frames whose lanes changed."""
    drawn = [record["illusion"] for record in records if "pred_points" in record["illusion"]]
    return {**illusion.identity(), "frames": len(drawn), "passed_through": len(records) - len(drawn),
            "layouts": len({entry["layout"] for entry in drawn if entry.get("layout") is not None}),
            "lanes_lost": sum(entry["lost"] for entry in drawn), "lanes_added": sum(entry["added"] for entry in drawn),
            "frames_changed": sum(bool(entry["lost"] or entry["added"]) for entry in drawn),
            "mean_accuracy": round(float(np.mean([entry["accuracy"] for entry in drawn])), 6) if drawn else None}
