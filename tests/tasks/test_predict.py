"""task=predict on your own frames: a folder (nested), a video written here by OpenCV (its frame count, the annotated
video's frames, fps and size, the TuSimple file scored by our metric command), a folder resumed, an unreadable image
named and skipped, a video with no frames and a list's missing image refused before work, bad settings refused by
the config check."""

from __future__ import annotations

import io
import json
import logging
from contextlib import redirect_stdout

import cv2
import numpy as np
import pytest
import torch

from lanevil_train.lanes import default_h_samples
from lanevil_train.metrics.__main__ import main as metrics_main
from lanevil_train.models.factory import load_detector
from lanevil_train.predict import PALETTE, draw_lanes, open_source
from lanevil_train.results_log import ResultsLog
from lanevil_train.sim import render_scene
from lanevil_train.tasks.config_check import ConfigError, check_config
from tests.tasks.cli_helpers import composed, run_in_process

SIZE = (90, 160)  # the frames' height and width


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """An untrained LaneATT at a tiny input, its head set to propose every anchor at full length with a score of
    0.9, so that it predicts lanes (saved as task=train saves a model: weights + build config)."""
    from lanevil_train.models.factory import DetectorSpec, create_detector
    from lanevil_train.tasks.builders import model_config

    torch.manual_seed(0)
    cfg = composed(["model=laneatt", "backbone=resnet18", "data.input_size=[64,128]"])
    model = create_detector(DetectorSpec.from_build_config(model_config(cfg)))
    head = model.head
    with torch.no_grad():
        for layer in (head.cls_layer, head.reg_layer):
            layer.weight.zero_()
            layer.bias.zero_()
        head.cls_layer.bias[1] = float(np.log(9.0))  # softmax score 0.9
        head.reg_layer.bias[0] = float(head.n_offsets)  # every anchor's full length
    path = tmp_path_factory.mktemp("model") / "tiny.ckpt"
    torch.save({"state_dict": model.state_dict(), "lanevil_model": model.build_config}, path)
    return path


def scene(seed: int) -> dict:
    sample = render_scene(seed, width=SIZE[1], height=SIZE[0])
    return {"image": cv2.cvtColor(sample["image"], cv2.COLOR_RGB2BGR), "lanes": sample["lanes"]}


def predict(checkpoint, source, out, *extra, run_dir=None):
    return run_in_process(["task=predict", f"ckpt_path={checkpoint}", f"task.input={source}", f"task.out_dir={out}",
                           "progress=none", "trainer.accelerator=cpu", *extra], run_dir or out.parent / "run")


def summary(out) -> dict:
    return json.loads((out / "summary.json").read_text())


def test_a_nested_folder_gets_drawn_frames_lanes_and_prediction_files_and_resumes_without_work(checkpoint, tmp_path):
    names = ["a.jpg", "sub/b.png", "sub/deeper/c.BMP"]
    for i, name in enumerate(names):
        (tmp_path / "photos" / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(tmp_path / "photos" / name), scene(10 + i)["image"])
    out = tmp_path / "photos" / "predicted"  # inside the input: its drawn frames are not taken as input
    predict(checkpoint, tmp_path / "photos", out)

    records = ResultsLog(out / "per_frame.jsonl").records()
    assert [r["key"] for r in records] == names  # sorted, recursive, any case of the extension
    for record in records:
        assert (record["height"], record["width"]) == SIZE and record["h_samples"] == list(default_h_samples(90))
        assert record["pred_points"] and len(record["scores"]) == len(record["pred_points"])
        assert all(score == pytest.approx(0.9, abs=1e-4) for score in record["scores"])
        points = np.concatenate([np.asarray(p) for p in record["pred_points"]])
        assert points[:, 0].min() >= -1 and points[:, 0].max() <= SIZE[1] + 1 and points[:, 1].max() <= SIZE[0] + 1
        assert record["run_time"] > 0
    expected = load_detector(checkpoint).predict(cv2.imread(str(tmp_path / "photos" / names[1])))  # the Python API
    assert len(records[1]["pred_points"]) == len(expected)
    for points, lane in zip(records[1]["pred_points"], expected):
        np.testing.assert_allclose(points, lane.points, atol=1e-3)
    for name, drawn in zip(names, ["a.jpg", "sub/b.jpg", "sub/deeper/c.jpg"]):
        image, original = cv2.imread(str(out / "frames" / drawn)), cv2.imread(str(tmp_path / "photos" / name))
        assert image.shape[:2] == SIZE and np.abs(image.astype(int) - original).max() > 100  # lanes drawn
    tusimple = [json.loads(line) for line in (out / "predictions" / "pred_tusimple.json").read_text().splitlines()]
    assert [line["raw_file"] for line in tusimple] == names and all(line["lanes"] for line in tusimple)
    assert (out / "predictions" / "culane" / "list.txt").read_text().split() == [f"/{n}" for n in names]
    assert (out / "predictions" / "culane" / "sub" / "deeper" / "c.lines.txt").is_file()

    files = {path: path.read_bytes() for path in out.rglob("*") if path.is_file() and path.name != "summary.json"}
    predict(checkpoint, tmp_path / "photos", out)  # the resume: every frame is in per_frame.jsonl already
    assert summary(out)["predicted"] == 0 and summary(out)["already_done"] == 3
    assert {path: path.read_bytes() for path in files} == files
    assert {p for p in out.rglob("*") if p.is_file() and p.name != "summary.json"} == set(files)


def test_a_video_gets_an_annotated_video_of_its_frames_and_a_tusimple_file_our_metric_scores(checkpoint, tmp_path):
    frames = [scene(20 + i) for i in range(6)]
    video = tmp_path / "drive.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 12.0, (SIZE[1], SIZE[0]))
    for frame in frames:
        writer.write(frame["image"])
    writer.release()
    out = tmp_path / "out"
    predict(checkpoint, video, out)

    records = ResultsLog(out / "per_frame.jsonl").records()
    keys = [f"frame_{i:06d}" for i in range(6)]
    assert [r["key"] for r in records] == keys and [r["frame"] for r in records] == list(range(6))
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"{k}.jpg" for k in keys]
    capture = cv2.VideoCapture(str(out / "drive_lanes.mp4"))
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(12.0)
    read = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        read.append(image)
    capture.release()
    assert len(read) == 6 and all(image.shape[:2] == SIZE for image in read)
    assert not list(out.glob(".*partial*"))  # the temporary was renamed

    gt = tmp_path / "label.json"  # the simulator's lanes of each frame, as a TuSimple label file
    rows = default_h_samples(SIZE[0])
    from lanevil_train.lanes import lanes_to_rows

    gt.write_text("".join(json.dumps({"raw_file": key, "h_samples": rows.astype(int).tolist(),
                                      "lanes": [[round(float(x), 1) if x >= 0 else -2 for x in lane]
                                                for lane in lanes_to_rows(frame["lanes"], rows)]}) + "\n"
                          for key, frame in zip(keys, frames)))
    pred = out / "predictions" / "pred_tusimple.json"
    for labels, expected in ((gt, None), (pred, 1.0)):  # against the scenes' lanes; against itself: all match
        stdout = io.StringIO()
        with redirect_stdout(stdout):
            assert metrics_main(["tusimple", "--pred", str(pred), "--gt", str(labels)]) == 0
        scores = json.loads(stdout.getvalue())
        assert 0.0 <= scores["Accuracy"] <= 1.0 and {"FP", "FN", "F1"} <= set(scores)
        if expected is not None:
            assert scores["Accuracy"] == pytest.approx(expected) and scores["FP"] == 0

    predict(checkpoint, video, tmp_path / "strided", "task.stride=2", "task.max_frames=2", "task.format=tusimple",
            "task.write_frames=false")
    strided = ResultsLog(tmp_path / "strided" / "per_frame.jsonl").records()
    assert [r["key"] for r in strided] == ["frame_000000", "frame_000002"]
    capture = cv2.VideoCapture(str(tmp_path / "strided" / "drive_lanes.mp4"))
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(6.0)  # plays at the source's speed
    assert not (tmp_path / "strided" / "predictions" / "culane").exists()  # task.format=tusimple
    assert not (tmp_path / "strided" / "frames").exists()  # task.write_frames=false: the drawn frames in the video only

    resumed = tmp_path / "resumed"  # a video resumes: a run stopped after 3 frames, then the whole video
    predict(checkpoint, video, resumed, "task.max_frames=3")
    predict(checkpoint, video, resumed)
    assert (summary(resumed)["predicted"], summary(resumed)["redrawn"]) == (3, 3)  # the first 3 from their lines
    again = ResultsLog(resumed / "per_frame.jsonl").records()
    assert [r["key"] for r in again] == keys  # the same lanes as the uninterrupted run
    for one, other in zip(again, records):
        assert len(one["pred_points"]) == len(other["pred_points"]) and one["scores"] == pytest.approx(other["scores"])
        for a, b in zip(one["pred_points"], other["pred_points"]):
            np.testing.assert_allclose(a, b, atol=1e-3)
    assert cv2.VideoCapture(str(resumed / "drive_lanes.mp4")).get(cv2.CAP_PROP_FRAME_COUNT) == 6


def test_an_unreadable_image_is_named_and_skipped_and_counted_at_the_end(checkpoint, tmp_path, caplog):
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "good.jpg"), scene(30)["image"])
    (tmp_path / "photos" / "broken.jpg").write_bytes(b"not a jpeg " * 50)
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING):
        predict(checkpoint, tmp_path / "photos", out)
    assert "broken.jpg: cannot read" in caplog.text
    assert "1 of 2 frames unreadable, skipped: broken.jpg" in caplog.text
    assert [r["key"] for r in ResultsLog(out / "per_frame.jsonl").records()] == ["good.jpg"]
    assert summary(out)["unreadable"] == ["broken.jpg"]
    with pytest.raises(ValueError, match="per_frame.jsonl holds results of another .*stride was '1', now '2'"):
        predict(checkpoint, tmp_path / "photos", out, "task.stride=2")  # resuming another selection is refused


def test_a_video_with_no_frames_and_a_list_with_a_missing_image_are_refused_before_work(checkpoint, tmp_path):
    empty = tmp_path / "empty.mp4"
    cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (SIZE[1], SIZE[0])).release()
    with pytest.raises(ValueError, match=r"task.input=.*empty.mp4: .*a video with no frames"):
        predict(checkpoint, empty, tmp_path / "out")
    cv2.imwrite(str(tmp_path / "one.jpg"), scene(40)["image"])
    (tmp_path / "list.txt").write_text("one.jpg\n\n# a comment\nmissing/two.jpg\n")
    with pytest.raises(FileNotFoundError, match=r"list.txt:4: no such image missing/two.jpg"):
        predict(checkpoint, tmp_path / "list.txt", tmp_path / "out")
    assert not (tmp_path / "out" / "per_frame.jsonl").exists()


def test_a_list_file_with_stride_and_cap(tmp_path):
    for name in ("x.jpg", "y.jpg", "z.jpg"):
        cv2.imwrite(str(tmp_path / name), scene(50)["image"])
    (tmp_path / "list.txt").write_text(f"z.jpg\nx.jpg\n{tmp_path / 'y.jpg'}\n")
    source = open_source(tmp_path / "list.txt", stride=2)
    assert [key for key, _ in source] == ["z.jpg", str(tmp_path / "y.jpg")]  # the list's order, absolute kept
    assert [key for key, _ in open_source(tmp_path / "list.txt", max_frames=1)] == ["z.jpg"]


def drive(path, frames: int, size=(144, 256), fps=10.0, seed=3):
    """A video of a car driving down a straight simulated road (sim.scene_at), written by OpenCV, and a TuSimple
    label file of its frames' true lanes (raw_file frame_%06d)."""
    from lanevil_train.data.formats.tusimple import write_tusimple
    from lanevil_train.sim import build_scene, sample_scene_params, scene_at, shade_scene

    road = build_scene(seed, sample_scene_params(seed).replace(road="straight", weather="clear_noon"), size[1], size[0])
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (size[1], size[0]))
    labels = []
    for k in range(frames):
        view = scene_at(road, k * 50 / 3.6 / fps)  # at task.speed_kmh's default
        writer.write(cv2.cvtColor(shade_scene(view), cv2.COLOR_RGB2BGR))
        labels.append({"raw_file": f"frame_{k:06d}", "lanes": view.lanes()[0],
                       "h_samples": default_h_samples(size[0])})
    writer.release()
    return write_tusimple(labels, path.with_suffix(".json"))


def illusion_rows(video, frames: int) -> list[float]:
    """The mean image row where the annotated video's right half (with the illusion) differs from its left (clean),
    below the titles, in each frame (no lanes are drawn: the tests' threshold is above every score)."""
    capture = cv2.VideoCapture(str(video))
    rows = []
    for _ in range(frames):
        ok, frame = capture.read()
        assert ok
        width = frame.shape[1] // 2
        changed = np.abs(frame[:, width:].astype(int) - frame[:, :width].astype(int)).sum(axis=2) > 60
        changed[:30] = False  # the titles
        assert changed.mean() > 0.005, "the illusion is missing from a frame"
        rows.append(float(np.nonzero(changed)[0].mean()))
    capture.release()
    return rows


def test_an_illusion_on_a_video_lies_on_the_road_side_by_side_and_slides_toward_the_camera(checkpoint, tmp_path):
    video = tmp_path / "drive.mp4"
    labels = drive(video, 6)
    out = tmp_path / "out"
    args = ["task.illusion=road_crack", "task.severity=5", f"task.labels={labels}", "task.decode.conf_threshold=0.99"]
    predict(checkpoint, video, out, *args)

    done = summary(out)
    assert done["illusion"]["frames"] == 6 and done["illusion"]["passed_through"] == 0
    assert done["illusion"]["layouts"] == 1  # 6 frames at 10 fps and 50 km/h: 7 m, less than task.relayout_m
    annotated = cv2.VideoCapture(done["video"])
    assert int(annotated.get(cv2.CAP_PROP_FRAME_COUNT)) == 6
    assert int(annotated.get(cv2.CAP_PROP_FRAME_WIDTH)) == 2 * 256  # clean | illusion
    annotated.release()
    rows = illusion_rows(done["video"], 6)
    assert rows[-1] > rows[0] + 5 and all(b > a - 3 for a, b in zip(rows, rows[1:])), rows  # down, without jumps
    for record in ResultsLog(out / "per_frame.jsonl").records():
        entry = record["illusion"]
        assert entry["ground"] == "labels" and entry["layout"] == 0
        assert entry["pred_points"] == [] and (entry["kept"], entry["lost"], entry["added"]) == (0, 0, 0)
    assert (out / "predictions" / "illusion" / "pred_tusimple.json").is_file()

    before = (out / "per_frame.jsonl").read_text()
    predict(checkpoint, video, out, *args)  # resumed: every frame redrawn from its line, the illusion drawn again
    assert summary(out)["predicted"] == 0 and summary(out)["redrawn"] == 6
    assert (out / "per_frame.jsonl").read_text() == before
    assert illusion_rows(done["video"], 6) == pytest.approx(rows, abs=1.0)


def test_a_frame_without_a_ground_plane_is_passed_through_and_counted(checkpoint, tmp_path):
    labels = drive(tmp_path / "drive.mp4", 1)  # frame_000000's true lanes
    photos = tmp_path / "photos"
    photos.mkdir()
    capture = cv2.VideoCapture(str(tmp_path / "drive.mp4"))
    image = capture.read()[1]
    capture.release()
    cv2.imwrite(str(photos / "frame_000000.png"), image)
    cv2.imwrite(str(photos / "unlabelled.png"), image)
    raw = json.loads(labels.read_text())
    labels.write_text(json.dumps({**raw, "raw_file": "frame_000000.png"}) + "\n")
    out = tmp_path / "out"
    predict(checkpoint, photos, out, "task.illusion=vehicle", f"task.labels={labels}",
            "task.decode.conf_threshold=0.99")  # no predicted lanes: the unlabelled image has no ground

    records = {r["key"]: r["illusion"] for r in ResultsLog(out / "per_frame.jsonl").records()}
    assert records["frame_000000.png"]["ground"] == "labels" and records["frame_000000.png"]["layout"] is None
    assert records["unlabelled.png"]["passed_through"].startswith("no ground plane: lanes: need at least 2 usable")
    assert summary(out)["illusion"]["frames"] == 1 and summary(out)["illusion"]["passed_through"] == 1
    drawn = cv2.imread(str(out / "frames" / "unlabelled.jpg"))
    assert drawn.shape[1] == 2 * image.shape[1]
    assert np.abs(drawn[40:, :256].astype(int) - drawn[40:, 256:].astype(int)).max() < 40  # the clean frame twice


def test_lane_changes_count_kept_lost_and_added_lanes():
    from lanevil_train.predict.illusion import lane_changes

    ys = np.linspace(200, 700, 11)
    left, right, far = (np.stack([x0 + 0.3 * (ys - 200), ys], axis=1) for x0 in (300.0, 800.0, 1100.0))
    moved = left + [12.0, 0.0]  # within 20 px: kept
    # TuSimple's accuracy counts a row neither lane reaches (5 of the 56 rows at 720 px) as a match, as LaneEval does
    assert lane_changes([left, right], [moved, far], 720, 1280) == {"kept": 1, "lost": 1, "added": 1,
                                                                    "accuracy": pytest.approx((1 + 5 / 56) / 2)}
    assert lane_changes([left, right], [left + [12.0, 0.0]], 360, 640)["lost"] == 2  # 20 px at 1280 is 10 at 640


@pytest.mark.parametrize("override, message", [
    ("task.illusion=fog", "task.illusion: expected null or one of road_crack"),
    ("task.severity=6", "task.severity: expected an integer from 1 to 5, got 6"),
    ("task.speed_kmh=0", "task.speed_kmh: expected a number in (0, 300], got 0"),
    ("task.stride=0", "task.stride: expected an integer >= 1, got 0"),
    ("task.max_frames=-3", "task.max_frames: expected null or an integer >= 1, got -3"),
    ("task.format=jpeg", "task.format: expected one of tusimple, culane, both, got 'jpeg'"),
    ("task.input=/no/such/clip.mp4", "task.input: expected null or an image, a folder of images"),
])
def test_bad_settings_are_refused_by_the_config_check_naming_the_key(override, message, checkpoint):
    with pytest.raises(ConfigError) as error:
        check_config(composed(["task=predict", f"ckpt_path={checkpoint}", override]))
    assert [p for p in error.value.problems if p.startswith(message)], error.value.problems


def test_an_official_experiment_needs_no_dataset_folder():
    check_config(composed(["task=predict", "experiment=official_clrnet_culane"]))  # data.root: ??? is not read


def test_lanes_are_drawn_in_the_palette_with_their_score():
    image = np.zeros((90, 160, 3), np.uint8)
    lanes = [(np.array([[40.0, 89], [60, 30]]), 0.87), (np.array([[120.0, 89], [100, 30]]), 0.5)]
    drawn = draw_lanes(image, lanes, thickness=3)
    assert image.max() == 0  # a copy
    assert np.abs(drawn[55:65, 45:56].astype(int) - PALETTE[0]).sum(-1).min() < 60
    assert np.abs(drawn[55:65, 104:116].astype(int) - PALETTE[1]).sum(-1).min() < 60
    blank = draw_lanes(image, [lane for lane, _ in lanes], thickness=3)  # no score: no text
    assert (drawn != 0).any(-1).sum() > (blank != 0).any(-1).sum()


def test_a_published_file_predicts_under_its_official_experiment(tmp_path):
    """`task=predict experiment=official_ufld_culane ckpt_path=culane_18.pth task.input=a.jpg`, the file written as
    the official training saves it (tests/models/test_official_ufld.py), no data.root given."""
    from tests.models.test_official_ufld import CULANE, OfficialLayout, _official_file

    torch.manual_seed(0)
    path = _official_file(tmp_path / "culane_18.pth", OfficialLayout(*CULANE).eval())
    cv2.imwrite(str(tmp_path / "a.jpg"), cv2.resize(scene(60)["image"], (820, 295)))
    run_in_process(["task=predict", "experiment=official_ufld_culane", f"ckpt_path={path}",
                    f"task.input={tmp_path / 'a.jpg'}", f"task.out_dir={tmp_path / 'out'}", "progress=none",
                    "trainer.accelerator=cpu"], tmp_path / "run")
    record, = ResultsLog(tmp_path / "out" / "per_frame.jsonl").records()
    assert (record["key"], record["height"], record["width"]) == ("a.jpg", 295, 820)
    assert (tmp_path / "out" / "frames" / "a.jpg").is_file()
