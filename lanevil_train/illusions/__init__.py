"""The 14 environmental illusions of LanEvil++ (paper §3.3), rendered in world space at 5 severities.

    from lanevil_train.illusions import ILLUSIONS, CATEGORIES, apply_illusion
    perturbed = apply_illusion(image, lanes, "rail_shadow", severity=3, seed=0)

On a simulated scene pass `context=context_from_scene(build_scene(seed, params, w, h))` for the exact
geometry; on a photo the ground plane is recovered from the lanes (`context_from_lanes`). Any point of an illusion's
physical parameters renders too: `ILLUSIONS[name].parameters()` (typed, bounded by the range of its severities) and
`ILLUSIONS[name].render_point(image, ctx, point, seed)`.
"""

from lanevil_train.illusions.api import apply_illusion, apply_illusions
from lanevil_train.illusions.context import IllusionContext, context_from_scene
from lanevil_train.illusions.parameters import Parameter, ParameterSpace
from lanevil_train.illusions.recover import GroundPlaneError, context_from_lanes, fallback_context
from lanevil_train.illusions.registry import CATEGORIES, ILLUSIONS, SEVERITIES, Illusion, get_illusion
from lanevil_train.illusions.transform import IllusionTransform

__all__ = [
    "ILLUSIONS", "CATEGORIES", "SEVERITIES", "Illusion", "IllusionContext", "IllusionTransform", "Parameter",
    "ParameterSpace", "GroundPlaneError", "apply_illusion", "apply_illusions", "context_from_lanes",
    "context_from_scene", "fallback_context", "get_illusion",
]
