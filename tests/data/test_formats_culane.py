"""CULane list files and .lines.txt reading/writing."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from lanevil_train.data.formats import read_culane, write_culane, write_culane_lanes
from lanevil_train.data.formats.culane import lines_path_for, read_culane_lanes

REL = "driver_37_30frame/05181432_0203.MP4/00000.jpg"


def _image(root: Path, rel: str = REL) -> Path:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.zeros((4, 4, 3), np.uint8))
    return path


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_read_official_style_files(tmp_path):
    img = _image(tmp_path)
    _write(lines_path_for(img), "-20.4835 580 19.3893 570 58.1682 560 \n532.893 590 542.567 580 \n\n")
    _write(tmp_path / "list/test.txt", f"/{REL}\n")
    (rec,) = read_culane(tmp_path / "list/test.txt", tmp_path)
    assert rec["image_path"] == img and rec["rel_path"] == REL and rec["labeled"]
    assert rec["lines_path"] == img.parent / "00000.lines.txt"
    assert len(rec["lanes"]) == 2
    np.testing.assert_array_equal(rec["lanes"][0], [[-20.4835, 580], [19.3893, 570], [58.1682, 560]])
    np.testing.assert_array_equal(rec["lanes"][1], [[532.893, 590], [542.567, 580]])


def test_read_train_gt_style_list(tmp_path):
    img = _image(tmp_path)
    _write(lines_path_for(img), "1 2 3 4\n")
    mask = "/laneseg_label_w16/driver_37_30frame/05181432_0203.MP4/00000.png"
    _write(tmp_path / "list/train_gt.txt", f"/{REL} {mask} 0 1 1 0\n")
    (rec,) = read_culane(tmp_path / "list/train_gt.txt", tmp_path)
    assert rec["mask_path"] == tmp_path / mask.lstrip("/") and rec["exist"] == [0, 1, 1, 0]
    np.testing.assert_array_equal(rec["lanes"][0], [[3, 4], [1, 2]])  # sorted bottom-up


def test_round_trip_and_written_format(tmp_path):
    rng = np.random.default_rng(5)
    records = []
    for i in range(3):
        rel = f"driver_x/clip.MP4/{i:05d}.jpg"
        _image(tmp_path, rel)
        ys = np.arange(590.0, 300.0, -10.0)
        lanes = [np.stack([np.round(rng.uniform(-50, 1700) + rng.uniform(-2, 2) * (590 - ys), 3), ys], 1)
                 for _ in range(int(rng.integers(0, 5)))]
        records.append({"image_path": tmp_path / rel, "lanes": lanes})
    list_path = write_culane(records, tmp_path, tmp_path / "list/out.txt")
    assert list_path.read_text().splitlines()[0] == "/driver_x/clip.MP4/00000.jpg"
    back = read_culane(list_path, tmp_path)
    assert [r["image_path"] for r in back] == [r["image_path"] for r in records]
    for rec, got in zip(records, back):
        assert len(got["lanes"]) == len(rec["lanes"])
        for a, b in zip(rec["lanes"], got["lanes"]):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)  # 3 decimals written, 3 decimals in


def test_write_lanes_bottom_first_and_precision(tmp_path):
    top_first = np.array([[100.123456, 410.0], [90.5, 500.0], [80.0, 590.0]])
    path = write_culane_lanes([top_first, np.zeros((0, 2))], tmp_path / "a.lines.txt", decimals=3)
    assert path.read_text() == "80 590 90.5 500 100.123 410\n"
    np.testing.assert_allclose(read_culane_lanes(path)[0], [[80, 590], [90.5, 500], [100.123, 410]])


def test_write_train_gt_style_list(tmp_path):
    rec = {"rel_path": REL, "lanes": [np.array([[5.0, 20.0], [6.0, 10.0]])],
           "mask_path": tmp_path / "laneseg/a.png", "exist": [1, 1, 0, 0]}
    list_path = write_culane([rec], tmp_path, tmp_path / "list/train_gt.txt")
    assert list_path.read_text() == f"/{REL} /laneseg/a.png 1 1 0 0\n"
    assert (tmp_path / REL).with_suffix(".lines.txt").read_text() == "5 20 6 10\n"


@pytest.mark.parametrize(
    "content, message",
    [
        ("1 2 3 4\n1 2 3\n", r"00000.lines.txt:2: odd number of coordinates \(3\)"),
        ("1 2 3 4\n\n1 2 abc 4\n", r"00000.lines.txt:3: non-numeric coordinate 'abc'"),
        ("nan 2 3 4\n", r"00000.lines.txt:1: contains non-finite"),
    ],
)
def test_lines_errors_name_file_and_line(tmp_path, content, message):
    img = _image(tmp_path)
    _write(lines_path_for(img), content)
    _write(tmp_path / "list.txt", f"/{REL}\n")
    with pytest.raises(ValueError, match=message):
        read_culane(tmp_path / "list.txt", tmp_path)


def test_missing_image_and_missing_lines(tmp_path):
    _write(tmp_path / "list.txt", f"\n/{REL}\n")
    with pytest.raises(FileNotFoundError, match=r"list.txt:2: image .*00000.jpg not found"):
        read_culane(tmp_path / "list.txt", tmp_path)
    _image(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"list.txt:2: annotation .*00000.lines.txt not found"):
        read_culane(tmp_path / "list.txt", tmp_path)
    (rec,) = read_culane(tmp_path / "list.txt", tmp_path, require_labels=False)
    assert rec["lanes"] == [] and rec["labeled"] is False


def test_bad_list_lines(tmp_path):
    _image(tmp_path)
    _write(tmp_path / "list.txt", f"/{REL} /mask.png 1 1\n")
    with pytest.raises(ValueError, match=r"list.txt:1: expected .* \(1 or 6 fields\), got 4"):
        read_culane(tmp_path / "list.txt", tmp_path)
    _write(tmp_path / "list.txt", f"/{REL} /mask.png 1 1 2 0\n")
    with pytest.raises(ValueError, match=r"list.txt:1: lane existence flags must be 0/1"):
        read_culane(tmp_path / "list.txt", tmp_path)
    with pytest.raises(ValueError, match="record 0: image .* not under root"):
        write_culane([{"image_path": tmp_path.parent / "elsewhere.jpg", "lanes": []}], tmp_path, tmp_path / "l.txt")


def test_an_image_listed_twice_is_refused_naming_both_lines(tmp_path):
    img = _image(tmp_path)
    other = _image(tmp_path, REL.replace("00000", "00030"))
    for path in (img, other):
        _write(lines_path_for(path), "1 2 3 4\n")
    other_rel = REL.replace("00000", "00030")
    listing = _write(tmp_path / "list/test.txt", f"/{REL}\n/{other_rel}\n\n{REL}\n")  # with or without the '/'
    with pytest.raises(ValueError) as error:
        read_culane(listing, tmp_path)
    assert str(error.value) == (f"{listing}:4: image {REL} is listed twice (first at {listing}:1); "
                                "each image must appear once in a CULane list")


def test_a_utf8_bom_is_accepted_in_lists_and_lines_files(tmp_path):
    img = _image(tmp_path)
    lines_path_for(img).write_bytes(b"\xef\xbb\xbf1 2 3 4\n")
    (tmp_path / "list").mkdir()
    (tmp_path / "list/test.txt").write_bytes(b"\xef\xbb\xbf" + f"/{REL}\n".encode())
    (rec,) = read_culane(tmp_path / "list/test.txt", tmp_path)
    assert rec["image_path"] == img and rec["rel_path"] == REL
    np.testing.assert_array_equal(rec["lanes"][0], [[3, 4], [1, 2]])  # y descending
