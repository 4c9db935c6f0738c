"""An unreadable image is reported with its path AND the label file and line that named it."""

from __future__ import annotations

import re

import numpy as np
import pytest

from lanevil_train.data.datasets import CULaneDataset, TuSimpleDataset
from lanevil_train.data.formats import load_image, read_culane, read_tusimple, write_culane, write_tusimple
from lanevil_train.data.illusion_set import Plan, build_illusion_set, synthetic_cases
from lanevil_train.data.suites import IllusionSetDataset
from tests.tasks.cli_helpers import write_photo_dataset

SPOILERS = {"empty": (b"", "is empty (0 bytes)"),
            "text": (b"this is not a picture\n", "is not an image")}


@pytest.fixture()
def tusimple(tmp_path):
    root = tmp_path / "tusimple"
    write_tusimple(write_photo_dataset(root, [f"clips/{i}/20.jpg" for i in range(3)]), root / "labels.json")
    return root


@pytest.mark.parametrize("spoil", sorted(SPOILERS))
def test_tusimple_reader_names_label_line_and_image(tusimple, spoil):
    content, problem = SPOILERS[spoil]
    (tusimple / "clips/1/20.jpg").write_bytes(content)
    with pytest.raises(ValueError) as error:
        read_tusimple(tusimple / "labels.json", tusimple)
    assert str(error.value) == (f"{tusimple / 'labels.json'}:2: image {tusimple / 'clips/1/20.jpg'} "
                                f"(raw_file 'clips/1/20.jpg') {problem}" + ("" if spoil == "empty" else
                                " (no image format that OpenCV reads starts like it)"))


@pytest.mark.parametrize("spoil", sorted(SPOILERS))
def test_culane_reader_names_list_line_and_image(tmp_path, spoil):
    root = tmp_path / "culane"
    write_culane(write_photo_dataset(root, [f"d/v.MP4/{i:05d}.jpg" for i in range(3)]), root, root / "list/test.txt")
    content, problem = SPOILERS[spoil]
    (root / "d/v.MP4/00002.jpg").write_bytes(content)
    with pytest.raises(ValueError, match="^" + re.escape(f"{root / 'list/test.txt'}:3: "
                                                         f"image {root / 'd/v.MP4/00002.jpg'} {problem}")):
        read_culane(root / "list/test.txt", root)


def test_an_image_spoilt_after_reading_is_named_with_its_label_line_when_loaded(tusimple):
    dataset = TuSimpleDataset(tusimple, "labels.json")
    assert dataset[2]["image"].shape == (180, 320, 3)
    image = tusimple / "clips/2/20.jpg"
    image.write_bytes(b"")
    with pytest.raises(ValueError, match=rf"^{tusimple / 'labels.json'}:3: image {image} is empty \(0 bytes\)$"):
        dataset[2]


def test_a_truncated_jpeg_passes_the_cheap_check_and_is_named_when_decoded(tmp_path):
    root = tmp_path / "culane"
    write_culane(write_photo_dataset(root, ["d/v.MP4/00000.jpg"]), root, root / "list/test.txt")
    image = root / "d/v.MP4/00000.jpg"
    image.write_bytes(image.read_bytes()[:200])  # the JPEG header survives, the picture does not
    dataset = CULaneDataset(root, "list/test.txt")  # the signature check passes
    with pytest.raises(ValueError, match=rf"^{root / 'list/test.txt'}:1: image {image} cannot be decoded"):
        dataset[0]


def test_load_image_reads_a_good_file_and_names_a_missing_one(tusimple):
    image = load_image(tusimple / "clips/0/20.jpg")
    assert image.dtype == np.uint8 and image.shape == (180, 320, 3) and image.std() > 5
    with pytest.raises(FileNotFoundError, match=rf"^image {tusimple / 'nope.jpg'} not found$"):
        load_image(tusimple / "nope.jpg")


def test_an_illusion_set_image_spoilt_after_the_build_is_named_with_its_label_line(tmp_path):
    plan = Plan(illusions=("vehicle",), severities=(2,), size=(72, 128))
    build_illusion_set(synthetic_cases(1, 1000), plan, tmp_path, progress="none")
    dataset = IllusionSetDataset(tmp_path)
    assert [dataset.item_key(i) for i in range(len(dataset))] == [
        "images/sim-0001000-f0/original.png", "images/sim-0001000-f0/vehicle_s2_r0.png"]
    image = tmp_path / "images/sim-0001000-f0/vehicle_s2_r0.png"
    image.write_text("not a png")
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'labels.json'}:2: image {image} is not an image"):
        dataset[1]


def test_a_directory_where_an_image_or_annotation_should_be_is_named_as_one(tmp_path):
    root = tmp_path / "culane"
    write_culane(write_photo_dataset(root, [f"d/v.MP4/{i:05d}.jpg" for i in range(2)]), root, root / "list/test.txt")
    (root / "d/v.MP4/00001.lines.txt").unlink()
    (root / "d/v.MP4/00001.lines.txt").mkdir()
    with pytest.raises(ValueError, match="^" + re.escape(f"{root / 'list/test.txt'}:2: annotation "
                                                         f"{root / 'd/v.MP4/00001.lines.txt'} is a directory")):
        read_culane(root / "list/test.txt", root)
    (root / "d/v.MP4/00000.jpg").unlink()
    (root / "d/v.MP4/00000.jpg").mkdir()
    with pytest.raises(ValueError, match="^" + re.escape(f"{root / 'list/test.txt'}:1: "
                                                         f"image {root / 'd/v.MP4/00000.jpg'} "
                                                         f"is a directory, not an image file")):
        read_culane(root / "list/test.txt", root)
