"""IllusionTransform: an albumentations transform that adds an illusion, lanes passed along.

The lanes travel as keypoints whose last value is the lane index (a numeric label field, e.g.
`KeypointParams(format="xy", label_fields=["lane_ids"])`, as lanevil_train's data pipeline does);
the ground plane is recovered from them, and the keypoints themselves are left unchanged.
"""

from __future__ import annotations

import albumentations as A
import numpy as np

from lanevil_train.illusions.api import apply_illusion
from lanevil_train.illusions.recover import GroundPlaneError
from lanevil_train.illusions.registry import ILLUSIONS, SEVERITIES, check_severity, get_illusion
from lanevil_train.lanes import as_lane


class IllusionTransform(A.DualTransform):
    """Apply one of `names` (default: all 14) at a severity drawn from `severities`, with probability p.

    Images whose lanes cannot define a ground plane (fewer than two usable lanes) pass unchanged,
    unless `strict=True`, which raises instead.
    """

    def __init__(self, names: list[str] | None = None, severities: tuple[int, ...] = SEVERITIES,
                 strict: bool = False, p: float = 0.5, **recover_kwargs):
        super().__init__(p=p)
        self.names = list(names) if names is not None else list(ILLUSIONS)
        for name in self.names:
            get_illusion(name)
        self.severities = tuple(check_severity(s) for s in severities)
        self.strict = strict
        self.recover_kwargs = recover_kwargs

    @property
    def targets_as_params(self) -> list[str]:
        return ["image", "keypoints"]

    def get_params_dependent_on_data(self, params: dict, data: dict) -> dict:
        keypoints = np.asarray(data.get("keypoints", np.zeros((0, 3))), dtype=np.float64)
        lanes = []
        if keypoints.ndim == 2 and keypoints.shape[1] >= 3:
            ids = keypoints[:, -1]
            lanes = [as_lane(keypoints[ids == i, :2]) for i in np.unique(ids)]
        rng = self.random_generator
        return {"lanes": lanes, "name": self.names[int(rng.integers(len(self.names)))],
                "severity": self.severities[int(rng.integers(len(self.severities)))],
                "seed": int(rng.integers(2**31 - 1))}

    def apply(self, img: np.ndarray, lanes: list, name: str, severity: int, seed: int, **params) -> np.ndarray:
        try:
            return apply_illusion(img, lanes, name, severity, seed=seed, **self.recover_kwargs)
        except GroundPlaneError:
            if self.strict:
                raise
            return img

    def apply_to_keypoints(self, keypoints: np.ndarray, **params) -> np.ndarray:
        return keypoints  # the lanes are still there: the model has to see them

    def get_transform_init_args_names(self) -> tuple[str, ...]:
        return ("names", "severities", "strict")
