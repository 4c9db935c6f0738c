"""The kind of run decided once (tasks/kinds.py): task._target_ names one function per kind of model, and the
model config names its kind."""

from __future__ import annotations

import pytest
from hydra import compose

from lanevil_train.tasks.kinds import model_kind, task_target

pytestmark = pytest.mark.usefixtures("hydra_conf")  # tests/conftest.py


@pytest.mark.parametrize("task, model, expected", [
    ("train", "laneatt", "lanevil_train.tasks.detector.train.train"),
    ("train", "vlm/embedded", "lanevil_train.tasks.vlm.train.train_vlm"),
    ("evaluate", "clrnet", "lanevil_train.tasks.detector.evaluate.evaluate"),
    ("evaluate", "vlm/hf", "lanevil_train.tasks.vlm.evaluate.evaluate_vlm"),
    ("export", "scnn", "lanevil_train.tasks.detector.export.export"),
    ("report", "vlm/openai", "lanevil_train.tasks.report.report"),  # one function for any model
    ("compare", "ufld", "lanevil_train.tasks.compare.compare"),
])
def test_each_task_runs_the_function_of_the_models_kind(task, model, expected):
    cfg = compose(config_name="config", overrides=[f"task={task}", f"model={model}"])
    assert task_target(cfg) == expected


def test_every_shipped_model_names_its_kind():
    from pathlib import Path

    import lanevil_train.conf

    root = Path(lanevil_train.conf.__file__).parent / "model"
    for path in sorted(root.rglob("*.yaml")):
        option = path.relative_to(root).with_suffix("").as_posix()
        cfg = compose(config_name="config", overrides=[f"model={option}"])
        assert model_kind(cfg) == ("vlm" if option.startswith("vlm/") else "detector"), option


@pytest.mark.parametrize("task", ["export", "cross_domain"])  # cross_domain inherits evaluate's config, drops its vlm
def test_a_task_without_a_function_for_the_kind_says_which_kinds_it_runs(task):
    cfg = compose(config_name="config", overrides=[f"task={task}", "model=vlm/embedded"])
    with pytest.raises(ValueError, match=rf"task={task} runs detector models; this model is a vlm"):
        task_target(cfg)
