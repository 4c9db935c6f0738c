"""Shared test settings: offline, quiet, small."""

import os

import pytest

os.environ.setdefault("WANDB_MODE", "offline")
if os.environ.get("PYTEST_XDIST_WORKER"):
    # pytest-xdist runs one worker per core (pyproject's addopts): each worker's torch, and the processes its tests
    # start, on one thread, so that the workers do not fight over the cores
    os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("HYDRA_FULL_ERROR", "1")


@pytest.fixture(scope="module")
def hydra_conf():
    """One Hydra initialisation of the package's configs for a test module: compose() is then cheap. A module
    uses it with `pytestmark = pytest.mark.usefixtures("hydra_conf")`."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        yield
    GlobalHydra.instance().clear()
