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
