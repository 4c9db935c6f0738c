"""The words the QA templates (vlm/clips/qa.py) use for the simulator's names: illusions, lanes, markings, weather.

Each illusion has what it really is (the reference answer) and a note; what a question calls it is its cue group's
words (CUES: what a camera sees, shared by illusions of two natures). The names are the simulator's (sim/presets.py)
and the taxonomy's (taxonomy.py).
"""

from __future__ import annotations

from types import MappingProxyType


def _facts(is_: str, note: str, traffic: bool = False) -> dict:
    return {"is": is_, "note": note, "traffic": traffic}


ILLUSION_FACTS = MappingProxyType({
    "road_crack": _facts("cracks in the asphalt", "Cracks are damage to the road surface and do not guide traffic."),
    "road_repair": _facts("sealed tar repairs of the asphalt",
                         "Repairs run where the road was patched, not where the lanes are."),
    "tire_marks": _facts("tyre skid marks on the asphalt", "Skid marks are rubber left by braking vehicles."),
    "guard_rail": _facts("a metal guard rail on posts beside the road",
                        "The rail stands beside the road; the edge line is painted on the asphalt."),
    "pedestrian": _facts("pedestrians standing on the road",
                        "They hide parts of the lane line but do not move it.", traffic=True),
    "vehicle": _facts("stopped vehicles on the road",
                     "They hide parts of the lane line but do not move it.", traffic=True),
    "bicycle": _facts("cyclists with their bicycles",
                     "They hide parts of the lane line but do not move it.", traffic=True),
    "streetlight_shadow": _facts("shadows of street lamp poles",
                                "The lamps beside the road cast them across the asphalt."),
    "fence_shadow": _facts("shadows of a roadside fence", "The fence beside the road casts them."),
    "rail_shadow": _facts("shadows of a roadside rail", "The low sun casts the rail's bars along the lanes."),
    "wire_shadow": _facts("shadows of overhead wires", "Wires above the road cast thin shadows on it."),
    "sunlight_reflection": _facts("sunlight reflected by the road", "Glare changes brightness, not the lanes."),
    "streetlight_reflection": _facts("reflections of street lights on the road", "The road surface mirrors the lamps."),
    "vehicle_reflection": _facts("reflections of a vehicle on the road surface",
                                "A reflection is not an object on the road."),
})

# What a question calls an illusion: what a camera sees, shared by illusions of different natures, so that the words
# never say what it is (a "dark line" may be a crack or a shadow; only the pixels tell).
CUES = MappingProxyType({"dark": "dark lines", "bright": "bright streaks", "figures": "shapes of people or vehicles"})
CUE_GROUP = MappingProxyType({
    **dict.fromkeys(("road_crack", "road_repair", "tire_marks", "streetlight_shadow", "fence_shadow", "rail_shadow",
                     "wire_shadow"), "dark"),
    **dict.fromkeys(("guard_rail", "sunlight_reflection", "streetlight_reflection"), "bright"),
    **dict.fromkeys(("pedestrian", "vehicle", "bicycle", "vehicle_reflection"), "figures"),
})
# What an illusion is made of: light (a shadow or a reflection), a mark in the asphalt itself, or a real object
# standing on or beside the road. Each cue group holds two natures, so a question about one is answered both ways.
NATURES = MappingProxyType({"light": "shadows or reflections of light", "surface": "marks in the asphalt itself",
                            "object": "real objects standing on or beside the road"})
NATURE = MappingProxyType({
    **dict.fromkeys(("streetlight_shadow", "fence_shadow", "rail_shadow", "wire_shadow", "sunlight_reflection",
                     "streetlight_reflection", "vehicle_reflection"), "light"),
    **dict.fromkeys(("road_crack", "road_repair", "tire_marks"), "surface"),
    **dict.fromkeys(("guard_rail", "pedestrian", "vehicle", "bicycle"), "object"),
})

LANE_PLACES = MappingProxyType({
    "ego": "in the ego lane", "left": "in the left lane", "right": "in the right lane",
    "left_shoulder": "on the left shoulder", "right_shoulder": "on the right shoulder",
    "across": "across the lanes",
})

NUMBER_WORDS = ("zero", "one", "two", "three", "four", "five", "six")
ORDINALS = ("first", "second", "third", "fourth", "fifth", "sixth")

ROAD_SHAPES = MappingProxyType({
    "straight": "Straight and level.", "left_curve": "Curving to the left.", "right_curve": "Curving to the right.",
    "uphill": "Climbing uphill.", "downhill": "Going downhill.",
})

SCENE_KINDS_TEXT = MappingProxyType({"urban": "An urban street between buildings.",
                                     "highway": "A multi-lane highway.", "rural": "A rural road through fields."})

WEATHER_TEXT = MappingProxyType({
    "clear_noon": "It is a clear day around noon with bright sunlight.",
    "cloudy_noon": "It is a cloudy day with soft, diffuse light.",
    "wet_noon": "It is daytime under a partly cloudy sky after rain.",
    "soft_rain_noon": "It is raining lightly in daytime, with hazy visibility.",
    "sunset": "It is sunset, with low, warm sunlight.",
    "night": "It is night, with the road lit by street lamps and headlights.",
})

_MARKING_WORDS = MappingProxyType({
    "white_solid": "a solid white line", "white_dashed": "a dashed white line",
    "white_double_solid": "a double solid white line", "yellow_solid": "a solid yellow line",
    "yellow_dashed": "a dashed yellow line", "yellow_double_solid": "a double solid yellow line",
    "white_solid_dashed": "a white solid-and-dashed line (solid on the left, dashed on the right)",
    "yellow_solid_dashed": "a yellow solid-and-dashed line (solid on the left, dashed on the right)",
    "botts_dots": "a row of raised white dots (Botts' dots)", "none": "no painted line, only the road edge",
})


MARKING_NAMES = tuple(k for k in _MARKING_WORDS if k != "none")  # the painted types


def marking_text(marking: str) -> str:
    """A marking type name (sim/presets.py MARKING_STRIPES) in words: "a dashed white line"."""
    if marking not in _MARKING_WORDS:
        raise ValueError(f"marking: expected one of {', '.join(_MARKING_WORDS)}, got {marking!r}")
    return _MARKING_WORDS[marking]


def crossing_allowed(marking: str, from_side: str) -> bool:
    """Whether a vehicle on `from_side` ("left"/"right") of the marking may cross it: dashed lines and dots may
    be crossed; a solid-and-dashed pair only from its dashed side (the right stripe is the dashed one)."""
    marking_text(marking)
    if marking.endswith("solid_dashed"):
        return from_side == "right"
    return marking.endswith("dashed") or marking == "botts_dots"
