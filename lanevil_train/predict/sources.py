"""Frame sources: the frames of one image, a folder of images, a video or a list file, as (key, BGR image) pairs.

``open_source(path, stride, max_frames)`` picks the kind by the path and checks it before any work:

- an image (.jpg, .jpeg, .png, .bmp, any case): one frame, keyed by its file name;
- a folder: every image under it, recursively, sorted by path; keyed by the path relative to the folder (posix);
  a folder holding none is refused;
- a list file (.txt): one image path per line, relative to the list's folder or absolute (blank lines and lines
  starting with # are skipped); keyed by the line's path (an absolute one, or one leaving the list's folder, by its
  absolute path); every missing image is named by the list's file and line before any frame is read, a path listed
  twice too;
- anything else: a video, whatever cv2.VideoCapture reads; keyed ``frame_%06d`` by the frame's index in the video
  (from 0); a file OpenCV opens no frame of (an empty video, not a video at all) is refused.

``stride`` takes every k-th frame (of a video, or of the sorted images), ``max_frames`` the first n of those. A
source yields only the frames it could read: an image cv2 cannot decode (a corrupt file), or a frame inside a video
that fails to decode while later ones read, is named in a warning and in ``source.unreadable``, and skipped.
``source.selected`` counts the frames the stride and cap took (read, unreadable, or skipped as already done).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Collection, Iterator
from pathlib import Path, PurePosixPath

import cv2
import numpy as np

from lanevil_train.rules import Rule, check_settings, integer, null_or

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp")
LIST_EXTENSIONS = (".txt",)
FRAME_KEY = "frame_{:06d}"  # a video frame's key: its index in the video
FAILED_READS_AT_END = 5  # this many failed reads in a row end a video (a header may count frames it does not hold)


SELECTION_SETTINGS = {"stride": Rule("an integer >= 1 (every k-th frame)", integer(1).test),
                      "max_frames": null_or(integer(1))}


def check_selection(stride, max_frames) -> tuple[int, int | None]:
    """stride an integer >= 1, max_frames null or an integer >= 1."""
    check_settings(SELECTION_SETTINGS, {"stride": stride, "max_frames": max_frames}, "")
    return int(stride), None if max_frames is None else int(max_frames)


def is_image_file(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTENSIONS


def read_image(path: str | Path) -> np.ndarray | None:
    """The image at `path` as a uint8 HxWx3 BGR array (grey and 16-bit images converted), or None when it cannot be
    decoded (a corrupt or truncated file, not an image)."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)  # any file name, whatever the platform's encoding
    except OSError:
        return None
    if data.size == 0:
        return None
    image = cv2.imdecode(data, cv2.IMREAD_COLOR)
    return image if image is not None and image.ndim == 3 and image.shape[2] == 3 else None


class FrameSource:
    """The frames of one input (module docstring): iterate it for (key, BGR image) pairs, or call frames(skip=...)."""

    kind: str = ""
    is_video = False

    def __init__(self, path: Path, stride: int = 1, max_frames: int | None = None):
        self.path = Path(path)
        self.stride, self.max_frames = check_selection(stride, max_frames)
        self.unreadable: list[str] = []  # the frames that could not be read, by name, in order
        self.selected = 0  # the frames the last iteration's stride and cap took

    @property
    def total(self) -> int | None:
        """How many frames the stride and cap select (a video's from its header: an estimate; None if unknown)."""
        raise NotImplementedError

    def frames(self, skip: Collection[str] = ()) -> Iterator[tuple[str, np.ndarray]]:
        """(key, BGR image) of every selected, readable frame whose key is not in `skip`."""
        raise NotImplementedError

    def __iter__(self) -> Iterator[tuple[str, np.ndarray]]:
        return self.frames()

    def frame_name(self, key: str) -> str:
        """Where the drawn frame of `key` goes under the output's frames/ folder (a relative posix path, .jpg)."""
        return f"{key}.jpg"

    def _unreadable(self, name: str, why: str) -> None:
        self.unreadable.append(name)
        log.warning("%s: %s, skipped", name, why)


class ImageSource(FrameSource):
    """One image, a folder's images or a list file's: `entries` are (key, path) pairs in order."""

    def __init__(self, path: Path, entries: list[tuple[str, Path]], kind: str, stride: int = 1,
                 max_frames: int | None = None):
        super().__init__(path, stride, max_frames)
        self.kind = kind
        self.entries = entries[::self.stride][:self.max_frames]
        self._names = frame_names([key for key, _ in self.entries])

    @property
    def keys(self) -> list[str]:
        return [key for key, _ in self.entries]

    @property
    def total(self) -> int:
        return len(self.entries)

    def frames(self, skip: Collection[str] = ()) -> Iterator[tuple[str, np.ndarray]]:
        self.unreadable, self.selected = [], 0
        for key, path in self.entries:
            self.selected += 1
            if key in skip:
                continue
            image = read_image(path)
            if image is None:
                self._unreadable(key, f"cannot read {path} as an image (corrupt, truncated or not an image)")
                continue
            yield key, image

    def frame_name(self, key: str) -> str:
        return self._names[key]


class VideoSource(FrameSource):
    """A video file's frames, decoded in order with OpenCV; checked when made (a first frame must read)."""

    kind = "video"
    is_video = True

    def __init__(self, path: Path, stride: int = 1, max_frames: int | None = None):
        super().__init__(path, stride, max_frames)
        capture = cv2.VideoCapture(str(self.path))
        try:
            ok, first = capture.read() if capture.isOpened() else (False, None)
            fps = capture.get(cv2.CAP_PROP_FPS)
            count = capture.get(cv2.CAP_PROP_FRAME_COUNT)
        finally:
            capture.release()
        if not ok or first is None:
            raise ValueError(f"{self.path}: a video with no frames OpenCV can read (an empty or unreadable video; "
                             f"images end in {', '.join(IMAGE_EXTENSIONS)}, image lists in .txt)")
        self.size = (int(first.shape[0]), int(first.shape[1]))  # (height, width)
        self.fps_known = bool(np.isfinite(fps) and fps > 0)
        self.fps = float(fps) if self.fps_known else 25.0
        if not self.fps_known:
            log.warning("%s: its frame rate is not recorded; the annotated video is written at 25 fps", self.path)
        self.frame_count = int(count) if np.isfinite(count) and count > 0 else None  # the header's, may be off

    @property
    def total(self) -> int | None:
        if self.frame_count is None:
            return self.max_frames
        selected = math.ceil(self.frame_count / self.stride)
        return selected if self.max_frames is None else min(selected, self.max_frames)

    def frames(self, skip: Collection[str] = ()) -> Iterator[tuple[str, np.ndarray]]:
        """Decode the video in order: the frames the stride does not take (and those in `skip`) are grabbed and not
        converted; a failed read followed by a good one is an unreadable frame, FAILED_READS_AT_END in a row (or
        one past the header's count) the end."""
        self.unreadable, self.selected = [], 0
        capture = cv2.VideoCapture(str(self.path))
        failed: list[int] = []
        index = -1
        try:
            while self.max_frames is None or self.selected < self.max_frames:
                index += 1
                key = FRAME_KEY.format(index)
                wanted = index % self.stride == 0
                if wanted and key not in skip:
                    ok, image = capture.read()
                else:
                    ok, image = capture.grab(), None
                if not ok:
                    failed.append(index)
                    if len(failed) >= FAILED_READS_AT_END or (self.frame_count is not None
                                                              and index >= self.frame_count - 1):
                        break
                    continue
                for bad in failed:  # frames that failed to decode, with good ones after them
                    if bad % self.stride == 0 and (self.max_frames is None or self.selected < self.max_frames):
                        self.selected += 1
                        self._unreadable(f"{self.path.name} {FRAME_KEY.format(bad)}", "cannot decode this frame")
                failed = []
                if not wanted or (self.max_frames is not None and self.selected >= self.max_frames):
                    continue
                self.selected += 1
                if image is not None:
                    yield key, image
        finally:
            capture.release()
        last = index - len(failed)
        if self.frame_count is not None and failed and last + 1 < self.frame_count:
            log.info("%s: the video ends after frame %d; its header counts %d frames", self.path, last,
                     self.frame_count)


def frame_names(keys: list[str]) -> dict[str, str]:
    """The drawn frame's relative path of each key: the key with its extension replaced by .jpg (a leading / left
    out), or, where two keys would share that name (a.png and a.jpg), the key with .jpg appended."""
    def plain(key: str) -> str:
        return str(PurePosixPath(key.lstrip("/")).with_suffix(".jpg"))

    counts: dict[str, int] = {}
    for key in keys:
        counts[plain(key)] = counts.get(plain(key), 0) + 1
    return {key: plain(key) if counts[plain(key)] == 1 else key.lstrip("/") + ".jpg" for key in keys}


def folder_entries(folder: Path, exclude: Path | None = None) -> list[tuple[str, Path]]:
    """Every image under `folder` (recursively, extensions in any case), sorted by its relative posix path; those
    under `exclude` (the run's drawn frames, when the output lies inside the input) left out."""
    exclude = exclude.resolve() if exclude is not None else None
    found = []
    for root, dirs, files in os.walk(folder):
        if exclude is not None and Path(root).resolve() == exclude:
            dirs[:] = []
            continue
        dirs.sort()
        for name in files:
            path = Path(root) / name
            if is_image_file(path) and path.is_file():
                found.append((path.relative_to(folder).as_posix(), path))
    return sorted(found)


def list_entries(list_file: Path) -> list[tuple[str, Path]]:
    """The images a list file names, in its order; every missing one (and every path listed twice) is an error
    naming the file and line, all of them at once."""
    base = list_file.parent
    entries, problems, seen = [], [], {}
    for number, line in enumerate(list_file.read_text(encoding="utf-8").splitlines(), 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        given = Path(text)
        path = given if given.is_absolute() else base / given
        relative = os.path.normpath(text).replace(os.sep, "/")
        key = relative if not given.is_absolute() and not relative.startswith("..") else path.resolve().as_posix()
        if not path.is_file():
            problems.append(f"{list_file}:{number}: no such image {text}"
                            + ("" if given.is_absolute() else f" (relative paths are read from {base})"))
        elif key in seen:
            problems.append(f"{list_file}:{number}: {text} is listed already (line {seen[key]})")
        else:
            seen[key] = number
            entries.append((key, path))
    if problems:
        shown = problems[:10] + ([f"... and {len(problems) - 10} more"] if len(problems) > 10 else [])
        raise FileNotFoundError(f"{list_file}: {len(problems)} of its images cannot be used:\n  " + "\n  ".join(shown))
    if not entries:
        raise ValueError(f"{list_file}: an image list naming no image (one path a line)")
    return entries


def open_source(path: str | Path, stride: int = 1, max_frames: int | None = None,
                exclude: str | Path | None = None) -> FrameSource:
    """The frame source of `path` (module docstring), checked now: a missing path, an empty folder or list, a
    list's missing images, a video with no frames raise before any frame is processed. `exclude`: a folder whose
    images a folder input leaves out (the run's drawn frames, when the output lies inside the input)."""
    path = Path(path)
    check_selection(stride, max_frames)
    if path.is_dir():
        entries = folder_entries(path, Path(exclude) if exclude is not None else None)
        if not entries:
            raise ValueError(f"{path}: a folder with no images ({', '.join(IMAGE_EXTENSIONS)}, any case, "
                             f"searched recursively)")
        return ImageSource(path, entries, "folder", stride, max_frames)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file or folder (an image, a folder of images, a video or a list "
                                f"file is expected)")
    if is_image_file(path):
        return ImageSource(path, [(path.name, path)], "image", stride, max_frames)
    if path.suffix.lower() in LIST_EXTENSIONS:
        return ImageSource(path, list_entries(path), "list", stride, max_frames)
    return VideoSource(path, stride, max_frames)
