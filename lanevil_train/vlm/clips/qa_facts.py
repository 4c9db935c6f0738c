"""The words the QA templates (vlm/clips/qa.py) use for the simulator's names: illusions, lanes, markings, weather.

Each illusion has what it looks like to a camera (the misleading cue a question carries) and what it really is
(the reference answer). The names are the simulator's (sim/presets.py) and the taxonomy's (taxonomy.py).
"""

from __future__ import annotations

from types import MappingProxyType


def _facts(looks: str, looks_one: str, is_: str, is_one: str, note: str, traffic: bool = False) -> dict:
    return {"looks": looks, "looks_one": looks_one, "is": is_, "is_one": is_one, "note": note, "traffic": traffic}


ILLUSION_FACTS = MappingProxyType({
    "road_crack": _facts("dark jagged lines", "dark jagged line", "cracks in the asphalt", "a crack in the asphalt",
                         "Cracks are damage to the road surface and do not guide traffic."),
    "road_repair": _facts("dark glossy strips", "dark glossy strip", "sealed tar repairs of the asphalt",
                          "a sealed tar repair of the asphalt",
                          "Repairs run where the road was patched, not where the lanes are."),
    "tire_marks": _facts("dark curved streaks", "dark curved streak", "tyre skid marks on the asphalt",
                         "a tyre skid mark on the asphalt", "Skid marks are rubber left by braking vehicles."),
    "guard_rail": _facts("long bright lines along the road edge", "long bright line along the road edge",
                         "a metal guard rail on posts beside the road", "a metal guard rail beside the road",
                         "The rail stands beside the road; the edge line is painted on the asphalt."),
    "pedestrian": _facts("people standing on the lane line", "person standing on the lane line",
                         "pedestrians standing on the road", "a pedestrian standing on the road",
                         "They hide parts of the lane line but do not move it.", traffic=True),
    "vehicle": _facts("vehicles standing on the lane line", "vehicle standing on the lane line",
                      "stopped vehicles on the road", "a stopped vehicle on the road",
                      "They hide parts of the lane line but do not move it.", traffic=True),
    "bicycle": _facts("cyclists on the lane line", "cyclist on the lane line", "cyclists with their bicycles",
                      "a cyclist with a bicycle", "They hide parts of the lane line but do not move it.",
                      traffic=True),
    "streetlight_shadow": _facts("long dark slanting lines", "long dark slanting line",
                                 "shadows of street lamp poles", "the shadow of a street lamp pole",
                                 "The lamps beside the road cast them across the asphalt."),
    "fence_shadow": _facts("rows of dark stripes", "row of dark stripes", "shadows of a roadside fence",
                           "the shadow of a roadside fence", "The fence beside the road casts them."),
    "rail_shadow": _facts("dark straight lines", "dark straight line", "shadows of a roadside rail",
                          "the shadow of a rail beside the road", "The low sun casts the rail's bars along the lanes."),
    "wire_shadow": _facts("thin dark lines", "thin dark line", "shadows of overhead wires",
                          "the shadow of an overhead wire", "Wires above the road cast thin shadows on it."),
    "sunlight_reflection": _facts("bright glare patches", "bright glare patch", "sunlight reflected by the road",
                                  "sunlight reflected by the road", "Glare changes brightness, not the lanes."),
    "streetlight_reflection": _facts("bright streaks", "bright streak", "reflections of street lights on the road",
                                     "a reflection of a street light on the road",
                                     "The road surface mirrors the lamps."),
    "vehicle_reflection": _facts("mirror images of a vehicle", "mirror image of a vehicle",
                                 "reflections of a vehicle on the road surface",
                                 "a reflection of a vehicle on the road surface",
                                 "A reflection is not an object on the road."),
})

# What a question calls an illusion: what a camera sees, shared by illusions of different natures, so that the words
# never say what it is (a "dark line" may be a crack or a shadow; only the pixels tell). (plural, singular) by group.
CUES = MappingProxyType({"dark": ("dark lines", "dark line"), "bright": ("bright streaks", "bright streak"),
                         "figures": ("shapes of people or vehicles", "shape of a person or vehicle")})
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
# never the simulator's scene: the fourth option of the scene-kind question (every choice question has 4)
SCENE_KIND_DISTRACTOR = "An unpaved track through a forest."

SPEED_BANDS = ("Standing still.", "Slower than 20 km/h.", "Between 20 and 40 km/h.", "Between 40 and 60 km/h.",
               "Faster than 60 km/h.")

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
