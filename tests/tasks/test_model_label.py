"""A detector's name in results and reports (builders.model_label): computed in one place for every task."""

from types import SimpleNamespace

import pytest

from lanevil_train.tasks import builders

DETECTOR = SimpleNamespace(build_config={"model": {"name": "laneatt"}, "backbone": {"name": "resnet18"}})


@pytest.mark.parametrize("label, defense, expected", [
    (None, None, "laneatt-resnet18"),
    ("", "none", "laneatt-resnet18"),
    (None, "aam++", "laneatt-resnet18+aam++"),
    ("ours", "aam++", "ours"),  # task.label is the name as it is
])
def test_the_label_is_task_label_else_family_backbone_and_defense(label, defense, expected):
    assert builders.model_label(DETECTOR, label, defense) == expected


def test_a_model_without_a_build_config_needs_a_label():
    with pytest.raises(ValueError, match="without a build config naming its model and backbone .* set task.label"):
        builders.model_label(SimpleNamespace(build_config=None))
    assert builders.model_label(SimpleNamespace(build_config=None), "mine") == "mine"


def test_every_detector_task_uses_the_one_function():
    from lanevil_train.tasks import closed_loop
    from lanevil_train.tasks.detector import evaluate, profile, train

    assert all(module.model_label is builders.model_label for module in (closed_loop, evaluate, profile, train))
