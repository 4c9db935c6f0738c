"""TuSimple label reading/writing and load_image."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lanevil_train.data.formats import load_image, read_tusimple, write_tusimple
from lanevil_train.lanes import lane_x_at


def _image(root: Path, rel: str, bgr=(0, 0, 255)) -> Path:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.zeros((6, 8, 3), np.uint8)
    img[:] = bgr
    assert cv2.imwrite(str(path), img)
    return path


def _label(tmp_path: Path, lines: list[str], name: str = "label.json") -> Path:
    path = tmp_path / name
    path.write_text("".join(line + "\n" for line in lines))
    return path


GOOD = json.dumps({"lanes": [[-2, -2, 100, 110], [400, 390, 380, -2]], "h_samples": [160, 170, 180, 190],
                   "raw_file": "clips/0/20.png"})


def test_read_converts_rows_to_lanes(tmp_path):
    _image(tmp_path, "clips/0/20.png")
    (rec,) = read_tusimple(_label(tmp_path, [GOOD]), tmp_path)
    assert rec["raw_file"] == "clips/0/20.png" and rec["image_path"] == tmp_path / "clips/0/20.png"
    np.testing.assert_array_equal(rec["lanes"][0], [[110, 190], [100, 180]])  # y descending, -2 dropped
    np.testing.assert_array_equal(rec["lanes"][1], [[380, 180], [390, 170], [400, 160]])
    np.testing.assert_array_equal(rec["h_samples"], [160, 170, 180, 190])
    assert rec["source"].endswith("label.json:1")


def test_read_several_files_blank_lines_and_empty_lanes(tmp_path):
    _image(tmp_path, "clips/0/20.png")
    _image(tmp_path, "clips/0/21.png")  # another image: one image on two lines is an error (test below)
    empty = json.dumps({"lanes": [[-2, -2, -2, -2], [1, 2, 3, 4]], "h_samples": [160, 170, 180, 190],
                        "raw_file": "clips/0/21.png"})
    a = _label(tmp_path, [GOOD, ""], "a.json")
    b = _label(tmp_path, [empty], "b.json")
    recs = read_tusimple([a, b], tmp_path)
    assert len(recs) == 2 and len(recs[1]["lanes"]) == 1
    kept = read_tusimple(b, tmp_path, keep_empty=True)[0]["lanes"]
    assert len(kept) == 2 and kept[0].shape == (0, 2)


def test_round_trip_int_and_float(tmp_path):
    ys = np.arange(160, 720, 10.0)
    lanes = [np.stack([300 + 0.37 * (720 - y), y], 1) for y in [np.arange(700, 250, -23.0)]]
    lanes.append(np.array([[900.4, 705.0], [1000.6, 300.0]]))
    rec = {"raw_file": "clips/1/20.jpg", "lanes": lanes, "h_samples": ys}
    out = write_tusimple([rec], tmp_path / "gt.json")
    line = json.loads(out.read_text())
    assert all(isinstance(x, int) for row in line["lanes"] for x in row) and line["h_samples"][0] == 160
    back = read_tusimple(out, tmp_path, check_images=False)[0]
    for orig, got in zip(lanes, back["lanes"]):
        expect = lane_x_at(orig, ys)
        got_x = lane_x_at(got, ys)
        assert np.array_equal(expect >= 0, got_x >= 0)
        assert np.max(np.abs(expect - got_x)[expect >= 0]) <= 0.5
    # floats: exact at the h_samples
    write_tusimple([rec | {"run_time": 12.5}], tmp_path / "pred.json", int_x=False)
    obj = json.loads((tmp_path / "pred.json").read_text())
    assert obj["run_time"] == 12.5
    back = read_tusimple(tmp_path / "pred.json", tmp_path, check_images=False)[0]
    for orig, got in zip(lanes, back["lanes"]):
        np.testing.assert_allclose(lane_x_at(got, ys), lane_x_at(orig, ys), atol=1e-9)


def test_write_marks_negative_x_invalid_and_appends(tmp_path):
    rec = {"raw_file": "a.jpg", "lanes": [np.array([[-30.0, 190], [10.0, 170], [50.0, 160]])],
           "h_samples": [160, 170, 180, 190]}
    path = write_tusimple([rec], tmp_path / "x.json")
    assert json.loads(path.read_text())["lanes"] == [[50, 10, -2, -2]]  # -10 and -30 are off-image
    write_tusimple([rec], path, append=True)
    assert len(path.read_text().splitlines()) == 2
    assert not list(tmp_path.glob(".x.json*"))  # no temp files left behind


def test_write_bad_record_names_index(tmp_path):
    with pytest.raises(ValueError, match="record 1: missing 'raw_file'"):
        write_tusimple([{"raw_file": "a", "lanes": []}, {"lanes": []}], tmp_path / "y.json")
    assert not (tmp_path / "y.json").exists()


@pytest.mark.parametrize(
    "line, message",
    [
        ('{"lanes": [[1, 2]], "h_samples": [1, 2], "raw_file": "a.png"', r"label.json:2: malformed JSON"),
        ('{"lanes": [[1, 2]], "raw_file": "a.png"}', r"label.json:2: missing key\(s\) \['h_samples'\]"),
        ('{"lanes": [[1, 2, 3]], "h_samples": [1, 2], "raw_file": "a.png"}',
         r"label.json:2: lane 0 has 3 x values but h_samples has 2"),
        ('{"lanes": [[1, "x"]], "h_samples": [1, 2], "raw_file": "a.png"}',
         r"label.json:2: lane 0 must be a list of numbers"),
        ('[1, 2]', r"label.json:2: expected a JSON object"),
    ],
)
def test_read_errors_name_file_and_line(tmp_path, line, message):
    _image(tmp_path, "clips/0/20.png")
    with pytest.raises(ValueError, match=message):
        read_tusimple(_label(tmp_path, [GOOD, line]), tmp_path)


def test_missing_image_and_label_file(tmp_path):
    label = _label(tmp_path, [GOOD])
    with pytest.raises(FileNotFoundError, match=r"label.json:1: image .*clips/0/20.png"):
        read_tusimple(label, tmp_path)
    assert len(read_tusimple(label, tmp_path, check_images=False)) == 1
    with pytest.raises(FileNotFoundError, match="missing.json"):
        read_tusimple(tmp_path / "missing.json", tmp_path)


def test_load_image_rgb_and_errors(tmp_path):
    path = _image(tmp_path, "red.png", bgr=(0, 0, 255))
    img = load_image(path)
    assert img.dtype == np.uint8 and img.shape == (6, 8, 3)
    assert tuple(img[0, 0]) == (255, 0, 0)  # RGB
    with pytest.raises(FileNotFoundError, match="nothing.png"):
        load_image(tmp_path / "nothing.png")
    junk = tmp_path / "junk.jpg"
    junk.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="junk.jpg"):
        load_image(junk)


def _line(raw_file: str = "clips/0/20.png", h_samples=(160, 170, 180, 190)) -> str:
    return json.dumps({"lanes": [[-2, -2, 100, 110]], "h_samples": list(h_samples), "raw_file": raw_file})


def test_an_image_on_two_lines_is_refused_naming_both(tmp_path):
    _image(tmp_path, "clips/0/20.png")
    _image(tmp_path, "clips/0/21.png")
    one = _label(tmp_path, [_line(), _line("clips/0/21.png"), "", _line()], "one.json")
    with pytest.raises(ValueError) as error:
        read_tusimple(one, tmp_path)
    assert str(error.value) == (f"{one}:4: raw_file 'clips/0/20.png' appears twice (first at {one}:1); "
                                "each image must have one label line")
    a = _label(tmp_path, [_line()], "a.json")
    b = _label(tmp_path, [_line("clips/0/21.png"), _line("./clips/0/20.png")], "b.json")  # across files too
    with pytest.raises(ValueError, match=rf"^{b}:2: raw_file './clips/0/20.png' appears twice \(first at {a}:1\)"):
        read_tusimple([a, b], tmp_path)


@pytest.mark.parametrize("h_samples,message", [
    ((160, 170, 170, 190), "h_samples repeats value 170 (2 times); expected each row once"),
    ((160, 160, 160, 160), "h_samples repeats value 160 (4 times); expected each row once"),
    ((160, -10, 180, 190), "h_samples contains negative value -10; expected image rows y >= 0"),
    ((160, 170, 180, -0.5), "h_samples contains negative value -0.5; expected image rows y >= 0"),
])
def test_negative_or_repeated_h_samples_are_refused_naming_line_and_value(tmp_path, h_samples, message):
    path = _label(tmp_path, [_line(h_samples=h_samples)])
    with pytest.raises(ValueError) as error:
        read_tusimple(path, tmp_path, check_images=False)
    assert str(error.value) == f"{path}:1: {message}"


def test_unsorted_h_samples_are_accepted(tmp_path):
    (rec,) = read_tusimple(_label(tmp_path, [_line(h_samples=(190, 160, 180, 170))]), tmp_path, check_images=False)
    assert rec["h_samples"].tolist() == [190, 160, 180, 170] and len(rec["lanes"]) == 1


def test_a_utf8_bom_is_accepted(tmp_path):
    _image(tmp_path, "clips/0/20.png")
    path = tmp_path / "bom.json"
    path.write_bytes(b"\xef\xbb\xbf" + (GOOD + "\n").encode())
    (rec,) = read_tusimple(path, tmp_path)
    assert rec["raw_file"] == "clips/0/20.png" and rec["source"] == f"{path}:1"
