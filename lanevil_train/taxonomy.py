"""The illusion taxonomy of the paper (§3.3): 4 categories, 14 illusion types, severities 1..5.

The one place the names live. It depends on nothing, so the renderers (illusions/), the result
records and reports (report/) and any future consumer read the same table.
"""

from __future__ import annotations

from types import MappingProxyType

SEVERITIES: tuple[int, ...] = (1, 2, 3, 4, 5)

# category -> illusion names, in the paper's order
CATEGORIES = MappingProxyType({
    "road_damage": ("road_crack", "road_repair", "tire_marks", "guard_rail"),
    "traffic_obstruction": ("pedestrian", "vehicle", "bicycle"),
    "shadow": ("streetlight_shadow", "fence_shadow", "rail_shadow", "wire_shadow"),
    "reflection": ("sunlight_reflection", "streetlight_reflection", "vehicle_reflection"),
})

# every illusion name, in the paper's order, and its category
ILLUSION_NAMES: tuple[str, ...] = tuple(name for names in CATEGORIES.values() for name in names)
ILLUSION_CATEGORY = MappingProxyType({name: category for category, names in CATEGORIES.items() for name in names})

# combined illusions (paper §5.6): a pair is named "<a>+<b>", its category "<category a>+<category b>", and the
# paper's tables write the category pair short, e.g. RD+TO
PAIR = "+"
CATEGORY_SHORT = MappingProxyType({"road_damage": "RD", "traffic_obstruction": "TO", "shadow": "SH",
                                   "reflection": "RF"})


PAIR_CATEGORIES: tuple[str, ...] = tuple(f"{a}{PAIR}{b}" for i, a in enumerate(CATEGORIES)
                                         for b in tuple(CATEGORIES)[i + 1:])


def pair_label(category: str) -> str:
    """A pair category in the paper's short form: "road_damage+shadow" -> "RD+SH" (other names unchanged)."""
    return PAIR.join(CATEGORY_SHORT.get(part, part) for part in category.split(PAIR))
