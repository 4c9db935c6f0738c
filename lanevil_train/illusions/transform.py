"""IllusionTransform: an albumentations transform that adds an illusion, lanes passed along.

The lanes travel as keypoints whose last value is the lane index (a numeric label field, e.g.
`KeypointParams(format="xy", label_fields=["lane_ids"])`, as lanevil_train's data pipeline does);
the ground plane is recovered from them, and the keypoints themselves are left unchanged.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence

import albumentations as A
import numpy as np

from lanevil_train.illusions.api import apply_illusion
from lanevil_train.illusions.recover import GroundPlaneError, context_from_lanes
from lanevil_train.illusions.registry import ILLUSIONS, SEVERITIES, check_severity, get_illusion
from lanevil_train.lanes import as_lane


class IllusionTransform(A.DualTransform):
    """Apply one of `names` (default: all 14) at a severity drawn from `severities`, with probability p.

    Images whose lanes cannot define a ground plane (fewer than two usable lanes) pass unchanged,
    unless `strict=True`, which raises instead. `names` may be one name, `severities` one int; further
    keywords go to `context_from_lanes` (RECOVER_KEYWORDS; others are refused). It must run inside an
    `A.Compose` whose KeypointParams has exactly one label field, the lane index of each point (else ValueError).
    """

    def __init__(self, names: str | list[str] | None = None, severities: int | tuple[int, ...] = SEVERITIES,
                 strict: bool = False, p: float = 0.5, **recover_kwargs):
        super().__init__(p=p)
        self.names = _names(names)
        self.severities = _severities(severities)
        self.strict = strict
        unknown = sorted(set(recover_kwargs) - set(RECOVER_KEYWORDS))
        if unknown:
            raise ValueError(f"IllusionTransform got unknown keyword(s) {', '.join(map(repr, unknown))}; expected "
                             f"names, severities, strict, p, or the ground-plane keywords of context_from_lanes: "
                             f"{', '.join(RECOVER_KEYWORDS)}")
        self.recover_kwargs = recover_kwargs

    @property
    def targets_as_params(self) -> list[str]:
        return ["image", "keypoints"]

    def get_params_dependent_on_data(self, params: dict, data: dict) -> dict:
        self._check_keypoint_params()
        keypoints = np.asarray(data.get("keypoints", np.zeros((0, 3))), dtype=np.float64)
        lanes = []
        if keypoints.ndim == 2 and keypoints.shape[1] >= 3:
            ids = keypoints[:, -1]
            lanes = [as_lane(keypoints[ids == i, :2]) for i in np.unique(ids)]
        rng = self.random_generator
        return {"lanes": lanes, "name": self.names[int(rng.integers(len(self.names)))],
                "severity": self.severities[int(rng.integers(len(self.severities)))],
                "seed": int(rng.integers(2**31 - 1))}

    def _check_keypoint_params(self) -> None:
        """The last keypoint column is the lane index only with exactly one label field: else a ValueError."""
        processor = self.processors.get("keypoints")
        label_fields = list(processor.params.label_fields or []) if processor is not None else None
        if label_fields is not None and len(label_fields) == 1:
            return
        got = ("no KeypointParams (use it inside an A.Compose with keypoint_params)" if label_fields is None
               else f"KeypointParams with label_fields={label_fields}")
        raise ValueError(
            "IllusionTransform needs the lanes as keypoints labelled by lane index, i.e. exactly one label field: "
            "A.Compose([..., IllusionTransform(...), ...], keypoint_params=A.KeypointParams(format='xy', "
            "label_fields=['lane_ids'])) called with keypoints=<lane points> and lane_ids=<lane index of each "
            f"point>; got {got}")

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


# the keywords IllusionTransform passes on to context_from_lanes (all but the lanes and the image size)
RECOVER_KEYWORDS = tuple(inspect.signature(context_from_lanes).parameters)[2:]


def _names(names) -> list[str]:
    """`names` as a non-empty list of known illusion names (one string is one name), or a ValueError."""
    if names is None:
        return list(ILLUSIONS)
    if isinstance(names, str):
        names = [names]
    if not isinstance(names, Sequence) or isinstance(names, bytes) or not names:
        raise ValueError(f"names must be a non-empty list of illusion names (or None for all {len(ILLUSIONS)}), "
                         f"got {names!r}")
    for k, name in enumerate(names):
        if not isinstance(name, str):
            raise ValueError(f"names[{k}] must be an illusion name (a string), got {name!r}")
        get_illusion(name)
    return list(names)


def _severities(severities) -> tuple[int, ...]:
    """`severities` as a non-empty tuple of ints 1..5 (one int is one severity), or a ValueError."""
    if isinstance(severities, (int, np.integer)) and not isinstance(severities, bool):
        severities = (severities,)
    if not isinstance(severities, Sequence) or isinstance(severities, (str, bytes)) or not severities:
        raise ValueError(f"severities must be a non-empty list of severities 1..5, e.g. (3, 4, 5), "
                         f"got {severities!r}")
    out = []
    for k, severity in enumerate(severities):
        try:
            out.append(check_severity(severity))
        except ValueError as e:
            raise ValueError(f"severities[{k}]: {e}") from None
    return tuple(out)
