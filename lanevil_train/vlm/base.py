"""The one VLM interface every backend implements, and the checks on what it is given.

A clip is 6 frames (uint8 HxWx3 RGB arrays, consecutive camera positions); a question is plain text. A backend
answers a batch of (clip, question) pairs, and, where it can see token probabilities, gives the per-sample
negative log-likelihood of given answers (what LoRA fine-tuning and PAT++ optimise).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Iterator, Sequence

import numpy as np

Frames = Sequence[np.ndarray]


def check_frames(frames, where: str = "clip") -> list[np.ndarray]:
    """The frames as a list of uint8 HxWx3 arrays of one size, else a ValueError naming `where` and the frame."""
    if isinstance(frames, np.ndarray) and frames.ndim == 4:
        frames = list(frames)
    if not isinstance(frames, (list, tuple)) or not frames:
        raise ValueError(f"{where}: expected a non-empty list of frames (uint8 HxWx3 arrays), got "
                         f"{type(frames).__name__}")
    for i, frame in enumerate(frames):
        if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            got = (f"{frame.dtype} array {frame.shape}" if isinstance(frame, np.ndarray) else type(frame).__name__)
            raise ValueError(f"{where}: frame {i} must be a uint8 HxWx3 RGB array, got {got}")
        if frame.shape != frames[0].shape:
            raise ValueError(f"{where}: frame {i} is {frame.shape[:2]}, frame 0 is {frames[0].shape[:2]}; the frames "
                             f"of a clip share one size")
    return list(frames)


def check_clip_tensor(clips) -> None:
    """A float tensor of clips [B, frames, 3, H, W] with values in [0, 1] (what VLM training feeds, so gradients
    reach the pixels), else a ValueError saying what it is."""
    import torch

    if not torch.is_floating_point(clips) or clips.ndim != 5 or clips.shape[2] != 3 or clips.shape[1] < 1:
        raise ValueError(f"clips: expected a float tensor [B, frames, 3, H, W] with values in [0, 1], got a "
                         f"{clips.dtype} tensor {tuple(clips.shape)}")
    low, high = float(clips.detach().min()), float(clips.detach().max())
    if low < -1e-6 or high > 1 + 1e-6:
        raise ValueError(f"clips: expected pixel values in [0, 1], got values in [{low:.3g}, {high:.3g}]")


def is_clip_tensor(clips) -> bool:
    """Whether `clips` is a tensor (training's differentiable clips) rather than lists of uint8 frames."""
    return type(clips).__module__.startswith("torch") and hasattr(clips, "ndim")


def check_batch(clips: Sequence[Frames], questions: Sequence[str], answers: Sequence[str] | None = None) -> None:
    """One clip per question (and one answer per question when answers are given), every text a string; the clips
    uint8 frames, or one float tensor [B, frames, 3, H, W] in [0, 1] (check_clip_tensor)."""
    if len(clips) != len(questions):
        raise ValueError(f"{len(clips)} clips for {len(questions)} questions: expected one clip per question")
    texts = [("question", questions)] + ([("answer", answers)] if answers is not None else [])
    for name, values in texts:
        if answers is not None and len(values) != len(questions):
            raise ValueError(f"{len(values)} {name}s for {len(questions)} questions")
        for i, text in enumerate(values):
            if not isinstance(text, str):
                raise ValueError(f"{name} {i}: expected a string, got {type(text).__name__}")
    if is_clip_tensor(clips):
        check_clip_tensor(clips)
        return
    for i, clip in enumerate(clips):
        check_frames(clip, f"clip {i}")


class VLM(ABC):
    """A driving VLM: answers questions about clips.

    name: the model's label in tables; batch_size: how many (clip, question) pairs `answer` is given at once by
    the evaluation loop; reads_frames: whether it looks at the clips at all (the text-only baseline does not).
    """

    name: str = "vlm"
    batch_size: int = 1
    reads_frames: bool = True  # False: answers from the text alone (an evaluation then loads no frames for it)

    @abstractmethod
    def answer(self, clips: Sequence[Frames], questions: Sequence[str]) -> list[str]:
        """One answer (plain text, stripped) per (clip, question) pair, in order."""

    def answer_stream(self, clips: Sequence[Frames], questions: Sequence[str]) -> Iterator[tuple[int, str]]:
        """(index, answer) pairs as answers become available (any order): an evaluation appends each as it
        arrives, so an interrupted run loses at most the answers in flight. Default: `answer` in order."""
        yield from enumerate(self.answer(clips, questions))

    def answer_loss(self, clips: Sequence[Frames], questions: Sequence[str], answers: Sequence[str]):
        """Per-sample mean negative log-likelihood (a float tensor [B], differentiable, with gradients reaching
        the input embeddings) of each answer's tokens given its clip and question."""
        raise NotImplementedError(f"{type(self).__name__} cannot score answers: it gives no token probabilities "
                                  f"(use a local model, model=vlm/hf)")

    def identity(self) -> dict:
        """What makes two evaluations by this backend the same (a resumed results file must come from the same
        model and generation settings): plain JSON values."""
        return {"backend": type(self).__name__, "name": self.name}


class BlindVLM(VLM):
    """A VLM's "blind" baseline: the same model asked the same questions with every frame replaced by a uniform grey
    image of the same size. Driving VLMs often answer from text priors (DriveBench: text-only scores sit close to
    clean ones), so a score is only evidence of seeing when it beats this baseline."""

    GREY = 128

    def __init__(self, vlm: VLM):
        self.vlm = vlm
        self.name = f"{vlm.name}-blind"
        self.batch_size = vlm.batch_size

    def _grey(self, clips: Sequence[Frames]) -> list[list[np.ndarray]]:
        return [[np.full_like(frame, self.GREY) for frame in check_frames(clip, f"clip {i}")]
                for i, clip in enumerate(clips)]

    def answer(self, clips: Sequence[Frames], questions: Sequence[str]) -> list[str]:
        return self.vlm.answer(self._grey(clips), questions)

    def answer_stream(self, clips: Sequence[Frames], questions: Sequence[str]) -> Iterator[tuple[int, str]]:
        yield from self.vlm.answer_stream(self._grey(clips), questions)

    def answer_loss(self, clips: Sequence[Frames], questions: Sequence[str], answers: Sequence[str]):
        return self.vlm.answer_loss(self._grey(clips), questions, answers)

    def identity(self) -> dict:
        return {**self.vlm.identity(), "blind": True}
