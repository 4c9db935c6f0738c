"""Tiny random-weight VLMs of each Hugging Face family, built offline once per test session."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from lanevil_dev.tiny_vlm import build_tiny_vlm

# SmolVLM's processor refuses to start without the num2words package.
NEEDS = {"smolvlm": "num2words"}


def _missing_package(family: str) -> str | None:
    """The package `family`'s processor needs that is not installed, if any."""
    package = NEEDS.get(family)
    return package if package and importlib.util.find_spec(package) is None else None


@pytest.fixture(scope="session")
def tiny_vlm_dir(tmp_path_factory):
    """family -> directory of its tiny model, each built on first use and kept for the session."""
    built: dict[str, object] = {}

    def get(family: str):
        if (package := _missing_package(family)) is not None:
            pytest.skip(f"{family}'s processor needs the {package} package, which is not installed")
        if family not in built:
            built[family] = build_tiny_vlm(family, tmp_path_factory.mktemp("tiny_vlm") / family)
        return built[family]

    return get


@pytest.fixture(scope="session")
def tiny_hf_vlm(tiny_vlm_dir):
    """family -> an HFVLM on its tiny model (float32, CPU, 4 new tokens), loaded once per session."""
    from lanevil_train.vlm.backends.hf import HFVLM

    loaded: dict[str, HFVLM] = {}

    def get(family: str) -> HFVLM:
        if family not in loaded:
            loaded[family] = HFVLM(tiny_vlm_dir(family), dtype="float32", device="cpu", max_new_tokens=4)
        return loaded[family]

    return get


@pytest.fixture(scope="session")
def small_clips():
    """Two clips of 6 random 32x48 RGB frames (fixed seed)."""
    rng = np.random.default_rng(7)
    return [[rng.integers(0, 256, (32, 48, 3), dtype=np.uint8) for _ in range(6)] for _ in range(2)]

