"""task=build killed at any instant: a rerun gives the uninterrupted set, file for file and byte for byte.

Every test compares {relative path: sha256} of everything under the output folder (hidden files included, so a
left-over temporary fails it) with a build that was never interrupted.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

import lanevil_train.data.formats.builds as builds
import lanevil_train.data.illusion_set as illusion_set
import lanevil_train.files.atomic as atomic
from lanevil_train.data.formats.manifest import read_manifest
from lanevil_train.data.illusion_set import Plan, build_illusion_set, synthetic_cases
from lanevil_train.files.atomic import atomic_write_bytes, atomic_write_text, temporary_path
from lanevil_train.results_log import ResultsLog

CASES = (3, 4000)  # synthetic_cases(num_cases, first_seed)
PLAN = {"illusions": ("fence_shadow", "vehicle"), "severities": (1, 2), "size": (72, 128)}
TOTAL = CASES[0] * (1 + 2 * 2)  # per case: the original and 2 illusions x 2 severities

BUILD_SCRIPT = f"""
import sys
from lanevil_train.data.illusion_set import Plan, build_illusion_set, synthetic_cases
plan = Plan(**{PLAN!r}, label_format=sys.argv[2])
build_illusion_set(synthetic_cases(*{CASES!r}), plan, sys.argv[1], progress="none")
"""


def build(root: Path, label_format: str) -> dict:
    return build_illusion_set(synthetic_cases(*CASES), Plan(**PLAN, label_format=label_format), root,
                              progress="none")


def snapshot(root: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under root."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> dict[str, dict[str, str]]:
    """The reference: each label format's set built in one go."""
    out = {}
    for label_format in ("tusimple", "culane"):
        root = tmp_path_factory.mktemp(f"whole_{label_format}")
        assert build(root, label_format)["written"] == TOTAL
        out[label_format] = snapshot(root)
    assert sum(name.endswith(".png") for name in out["tusimple"]) == TOTAL
    assert set(out["culane"]) - set(out["tusimple"]) == {f"{name[:-4]}.lines.txt" for name in out["culane"]
                                                         if name.endswith(".png")} | {"list/test.txt"}
    return out


def manifest_lines(root: Path) -> int:
    """Finished manifest lines (a torn last line has no newline yet)."""
    try:
        return (root / "manifest.jsonl").read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def images_written_since(root: Path, start_ns: int) -> int:
    """Final images (a temporary would not match *.png) written at or after `start_ns`: by the running build."""
    return sum(p.stat().st_mtime_ns >= start_ns for p in root.glob("images/*/*.png"))


def kill_build_after(root: Path, label_format: str, images: int, delay_s: float) -> int:
    """Run a build in a subprocess and SIGKILL it `delay_s` after it has written `images` images (so somewhere in
    the next image's work, or in the label and manifest lines after a case's images); its exit code."""
    start_ns = time.time_ns()
    proc = subprocess.Popen([sys.executable, "-c", BUILD_SCRIPT, str(root), label_format],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while proc.poll() is None and images_written_since(root, start_ns) < images and time.monotonic() < deadline:
        time.sleep(0.0005)
    time.sleep(delay_s)
    proc.kill()  # nothing happens if it already exited
    _, stderr = proc.communicate()
    assert proc.returncode in (-signal.SIGKILL, 0), stderr.decode()
    return proc.returncode


def check_kills_then_rerun(root: Path, label_format: str, seed: int, kills: int, whole: dict[str, str]) -> None:
    """Kill a build `kills` times, each after a random number of the images it still has to write, then rerun it
    to the end in-process and compare with the uninterrupted build."""
    rng = random.Random(seed)
    done, where = 0, f"seed {seed}, {label_format}"
    for _ in range(kills):
        if done == TOTAL:
            break
        images, delay = rng.randint(1, TOTAL - done), rng.uniform(0, 0.005)
        where += f"; killed {delay * 1000:.1f} ms after image {images} of the {TOTAL - done} left"
        assert kill_build_after(root, label_format, images, delay) == -signal.SIGKILL, f"{where}: it had finished"
        done = manifest_lines(root)
    summary = build(root, label_format)
    assert (summary["skipped"], summary["written"]) == (done, TOTAL - done), where
    assert snapshot(root) == whole, where


@pytest.mark.parametrize("label_format,seed", [("tusimple", 11), ("culane", 12)])
def test_kill_9_at_a_random_image_then_rerun_equals_the_uninterrupted_build(tmp_path, uninterrupted,
                                                                            label_format, seed):
    check_kills_then_rerun(tmp_path / "set", label_format, seed, 1, uninterrupted[label_format])


@pytest.mark.slow
@pytest.mark.parametrize("label_format", ["tusimple", "culane"])
@pytest.mark.parametrize("seed", range(3))
def test_repeated_kills_then_rerun_equals_the_uninterrupted_build(tmp_path, uninterrupted, label_format, seed):
    check_kills_then_rerun(tmp_path / "set", label_format, 100 + seed, 4, uninterrupted[label_format])


class Killed(BaseException):
    """Stands for SIGKILL in-process: nothing after it runs (a BaseException, so no `except Exception` stops it)."""


def kill_before_write(monkeypatch, step: int | None) -> list[str]:
    """Make the build's `step`-th write (1-based: an image, a .lines.txt, a label line, a manifest line, the list)
    raise Killed before it happens; the names of the writes done (or tried) so far, filled in as the build runs."""
    calls: list[str] = []

    def wrap(name, write):
        def wrapped(*args, **kwargs):
            calls.append(name)
            if len(calls) == step:
                raise Killed
            return write(*args, **kwargs)
        return wrapped

    for name in ("atomic_write_bytes", "atomic_write_text", "write_culane_lanes", "_append_line", "write_build_record"):
        monkeypatch.setattr(illusion_set, name, wrap(name, getattr(illusion_set, name)))
    monkeypatch.setattr(builds, "write_build_record", wrap("write_build_record", builds.write_build_record))
    monkeypatch.setattr(ResultsLog, "append", wrap("manifest", ResultsLog.append))
    return calls


@pytest.mark.parametrize("label_format", ["tusimple", "culane"])
def test_a_kill_between_any_two_writes_then_rerun_equals_the_uninterrupted_build(tmp_path, label_format):
    """Every step boundary of a one-case build, in order: this pins the write order (image before its label line
    before its manifest line) that the random kills above only hit by chance."""
    plan, cases = Plan(**PLAN, label_format=label_format), synthetic_cases(1, 4000)
    with pytest.MonkeyPatch.context() as monkeypatch:
        steps = kill_before_write(monkeypatch, None)
        build_illusion_set(cases, plan, tmp_path / "whole", progress="none")
    whole = snapshot(tmp_path / "whole")
    # build.json (not complete) first and (complete) last
    if label_format == "tusimple":  # a case's images, then per image its label line and its manifest line
        assert steps == ["write_build_record"] + ["atomic_write_bytes"] * 5 + ["_append_line", "manifest"] * 5 \
            + ["write_build_record"]
    else:                           # per image its .lines.txt and the image, then the manifest lines, the list
        assert steps == ["write_build_record"] + ["write_culane_lanes", "atomic_write_bytes"] * 5 \
            + ["manifest"] * 5 + ["atomic_write_text", "write_build_record"]
    for step in range(1, len(steps) + 1):
        root = tmp_path / f"killed_before_{step}"
        with pytest.MonkeyPatch.context() as monkeypatch, pytest.raises(Killed):
            kill_before_write(monkeypatch, step)
            build_illusion_set(cases, plan, root, progress="none")
        build_illusion_set(cases, plan, root, progress="none")
        assert snapshot(root) == whole, f"killed before write {step} ({steps[step - 1]})"


def test_temporaries_are_hidden_partial_files_no_glob_for_final_files_matches(tmp_path):
    for name in ("original.png", "original.lines.txt", "labels.json"):
        tmp = temporary_path(tmp_path / name)
        assert re.fullmatch(rf"\.{re.escape(name)}\.{os.getpid()}\.[0-9a-f]{{8}}\.partial", tmp.name), tmp.name
        assert tmp.parent == tmp_path and tmp != temporary_path(tmp_path / name)
        tmp.write_bytes(b"")
    assert [p.name for p in tmp_path.glob("*.png")] == []
    assert [p.name for p in tmp_path.glob("*.txt")] == [] and [p.name for p in tmp_path.glob("*.json")] == []


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "labels.json"
    atomic_write_text(target, "old\n")

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", disk_full)
    with pytest.raises(OSError, match="No space left"):
        atomic_write_bytes(target, b"new\n")
    assert target.read_bytes() == b"old\n" and [p.name for p in tmp_path.iterdir()] == ["labels.json"]


def test_rerun_removes_stale_temporaries(tmp_path, uninterrupted):
    root = tmp_path / "set"
    build(root, "tusimple")
    folder = root / "images" / "sim-0004001-f0"
    stale = [temporary_path(folder / "vehicle_s2_r0.png"), temporary_path(folder / "original.png"),
             temporary_path(root / "labels.json")]
    stale[0].write_bytes(b"")                                                 # killed right after creating it
    stale[1].write_bytes((folder / "original.png").read_bytes()[:100])        # killed in the middle of the bytes
    stale[2].write_text('{"lanes": [[1, 2')
    assert build(root, "tusimple") == {"root": str(root), "images": TOTAL, "written": 0, "skipped": TOTAL}
    assert snapshot(root) == uninterrupted["tusimple"]
    assert not any(p.exists() for p in stale)


def simulate_kill(root: Path, label_format: str, image: int, inside: str) -> None:
    """Turn a finished set into what a kill while recording image number `image` (1-based) leaves: its image (and
    .lines.txt) written, the write cut `inside` its label line ("labels") or its manifest line ("manifest"), the
    later images not written yet."""
    lines = (root / "manifest.jsonl").read_text().splitlines(keepends=True)
    for line in lines[image:]:
        path = root / json.loads(line)["image"]
        path.unlink()
        path.with_suffix(".lines.txt").unlink(missing_ok=True)
    (root / "list" / "test.txt").unlink(missing_ok=True)
    half = lambda line: line[: len(line) // 2]  # noqa: E731
    torn_manifest = half(lines[image - 1]) if inside == "manifest" else ""
    (root / "manifest.jsonl").write_text("".join(lines[: image - 1]) + torn_manifest)
    if label_format == "tusimple":
        labels = (root / "labels.json").read_text().splitlines(keepends=True)
        last_label = labels[image - 1] if inside == "manifest" else half(labels[image - 1])
        (root / "labels.json").write_text("".join(labels[: image - 1]) + last_label)


@pytest.mark.parametrize("label_format,inside", [("tusimple", "manifest"), ("tusimple", "labels"),
                                                 ("culane", "manifest")])
def test_a_torn_last_line_is_cut_and_the_rerun_completes_identically(tmp_path, uninterrupted, label_format, inside):
    root = tmp_path / "set"
    build(root, label_format)
    simulate_kill(root, label_format, image=4, inside=inside)
    assert (root / "manifest.jsonl").read_text().count("\n") == 3
    if inside == "manifest":
        with pytest.raises(ValueError, match="manifest.jsonl:4: .*interrupted.*rerun task=build"):
            read_manifest(root / "manifest.jsonl")
    assert build(root, label_format) == {"root": str(root), "images": TOTAL, "written": TOTAL - 3, "skipped": 3}
    assert snapshot(root) == uninterrupted[label_format]


@pytest.mark.parametrize("umask,mode", [(0o022, 0o644), (0o027, 0o640)])
def test_written_files_get_the_mode_open_gives_them(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        for label_format in ("tusimple", "culane"):
            build_illusion_set(synthetic_cases(1, 4000), Plan(**PLAN, label_format=label_format),
                               tmp_path / label_format, progress="none")
        # a rerun rewrites labels.json (_repair_labels)
        build_illusion_set(synthetic_cases(1, 4000), Plan(**PLAN), tmp_path / "tusimple", progress="none")
        atomic_write_text(tmp_path / "text.txt", "x")
        atomic_write_bytes(tmp_path / "bytes.bin", b"x")
    finally:
        os.umask(old)
    modes = {p.relative_to(tmp_path).as_posix(): stat.S_IMODE(p.stat().st_mode)
             for p in tmp_path.rglob("*") if p.is_file()}
    assert len(modes) == 2 * 5 + 5 + 2 + 2 + 1 + 1 + 2  # images, .lines.txt, 2 manifests, 2 build.json,
    # labels.json, list, 2 files
    assert {"culane/list/test.txt", "tusimple/labels.json", "culane/manifest.jsonl", "tusimple/build.json",
            "culane/images/sim-0004000-f0/original.lines.txt"} <= set(modes)
    assert modes == dict.fromkeys(modes, mode)


def test_read_manifest_says_a_cut_off_last_line_means_an_interrupted_build(tmp_path):
    record = {"image": "images/a/original.png", "source_image": "images/a/original.png", "case_id": "a",
              "illusion": None, "category": None, "severity": 0, "seed": 0}
    line = json.dumps(record) + "\n"
    path = tmp_path / "out" / "manifest.jsonl"
    path.parent.mkdir()
    path.write_text(line * 2 + line[:30])
    with pytest.raises(ValueError) as error:
        read_manifest(path)
    assert str(error.value) == (f"{path}:3: the last line is cut off: the build that wrote this set was "
                                f"interrupted; rerun task=build with the same out_dir ({path.parent}) to finish it")
    path.write_text(line + line[:30] + "\n" + line)  # a bad line in the middle is corruption, not an interruption
    with pytest.raises(ValueError, match=r"manifest.jsonl:2: malformed JSON") as error:
        read_manifest(path)
    assert "interrupted" not in str(error.value)
    path.write_text(line * 2 + line[:-1])  # a whole last line without its newline is still read
    assert read_manifest(path) == [record] * 3
