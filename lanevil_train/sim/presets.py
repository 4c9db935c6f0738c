"""Named presets: marking types, weather / time-of-day looks and scene kinds (roadside dressing).

Colours are sRGB in 0..1. Everything here is plain data so that params.py can validate names and
render.py / shading.py can look them up.
"""

from __future__ import annotations

from types import MappingProxyType

from lanevil_train.sim.road import Stripe

ROAD_KINDS = ("straight", "left_curve", "right_curve", "s_curve", "uphill", "downhill")

# ----------------------------------------------------------------------------- markings
_W = 0.15  # single stripe width (m)
_DW = 0.12  # stripe width inside a double line
_DO = 0.12  # offset of each stripe of a double line from the marking centre

MARKING_STRIPES = MappingProxyType({
    "white_solid": (Stripe(0.0, _W, False),),
    "white_dashed": (Stripe(0.0, _W, True),),
    "white_double_solid": (Stripe(-_DO, _DW, False), Stripe(_DO, _DW, False)),
    "yellow_solid": (Stripe(0.0, _W, False),),
    "yellow_dashed": (Stripe(0.0, _W, True),),
    "yellow_double_solid": (Stripe(-_DO, _DW, False), Stripe(_DO, _DW, False)),
    "white_solid_dashed": (Stripe(-_DO, _DW, False), Stripe(_DO, _DW, True)),
    "yellow_solid_dashed": (Stripe(-_DO, _DW, False), Stripe(_DO, _DW, True)),
    "botts_dots": (Stripe(0.0, 0.2, True, dots=True),),
    "none": (),
})
MARKING_TYPES = tuple(k for k in MARKING_STRIPES if k != "none")  # the 9 painted types


def marking_color(marking: str) -> str:
    """'white', 'yellow' or 'none' for a marking type name."""
    if marking == "none":
        return "none"
    return "yellow" if marking.startswith("yellow") else "white"


PAINT_RGB = MappingProxyType({"white": (0.93, 0.93, 0.90), "yellow": (0.93, 0.72, 0.16)})
BOTTS_RGB = (0.90, 0.90, 0.86)

# ----------------------------------------------------------------------------- weather
# sky_zenith/sky_horizon: sky gradient; haze: colour distant things fade to; fog: e-folding
# distance (m); light: ambient light colour*intensity on the ground; wet: 0 dry .. 1 soaked;
# rain: streak density; sun: (elevation deg, azimuth deg, + right) for glow and later shadows;
# night: lamps/headlights/lit windows; clouds: cloud cover 0..1.
WEATHERS = MappingProxyType({
    "clear_noon": dict(sky_zenith=(0.23, 0.45, 0.82), sky_horizon=(0.70, 0.80, 0.92),
                       haze=(0.74, 0.80, 0.88), fog=900.0, light=(1.0, 1.0, 0.98), wet=0.0,
                       rain=0.0, sun=(60.0, 25.0), sun_glow=0.15, night=False, clouds=0.15),
    "cloudy_noon": dict(sky_zenith=(0.55, 0.58, 0.62), sky_horizon=(0.78, 0.79, 0.80),
                        haze=(0.74, 0.75, 0.77), fog=500.0, light=(0.80, 0.81, 0.83), wet=0.0,
                        rain=0.0, sun=(55.0, -30.0), sun_glow=0.0, night=False, clouds=0.85),
    "wet_noon": dict(sky_zenith=(0.45, 0.52, 0.62), sky_horizon=(0.76, 0.80, 0.84),
                     haze=(0.72, 0.75, 0.79), fog=450.0, light=(0.82, 0.84, 0.88), wet=1.0,
                     rain=0.0, sun=(50.0, 20.0), sun_glow=0.05, night=False, clouds=0.6),
    "soft_rain_noon": dict(sky_zenith=(0.48, 0.50, 0.54), sky_horizon=(0.66, 0.67, 0.69),
                           haze=(0.62, 0.63, 0.65), fog=160.0, light=(0.62, 0.63, 0.66), wet=1.0,
                           rain=0.5, sun=(50.0, 0.0), sun_glow=0.0, night=False, clouds=1.0),
    "sunset": dict(sky_zenith=(0.22, 0.26, 0.45), sky_horizon=(0.98, 0.58, 0.28),
                   haze=(0.85, 0.55, 0.38), fog=400.0, light=(0.85, 0.58, 0.40), wet=0.0,
                   rain=0.0, sun=(4.0, -20.0), sun_glow=0.9, night=False, clouds=0.3),
    "night": dict(sky_zenith=(0.01, 0.015, 0.04), sky_horizon=(0.05, 0.06, 0.10),
                  haze=(0.04, 0.045, 0.07), fog=250.0, light=(0.025, 0.028, 0.036), wet=0.0,
                  rain=0.0, sun=(-30.0, 0.0), sun_glow=0.0, night=True, clouds=0.0),
})
WEATHER_NAMES = tuple(WEATHERS)

# ----------------------------------------------------------------------------- scene kinds
# verge: what lies beyond the asphalt, as (width m, rgb, texture contrast) bands from the edge
# outwards; walls: vertical surfaces parallel to the road (distance beyond the verge start,
# kind); lamps: spacing (m) of street lamps (0 = none); default markings: (left, inner, right).
SCENE_KINDS = MappingProxyType({
    "urban": dict(shoulder=(0.4, 1.0), verge=((0.25, (0.70, 0.70, 0.68), 0.10),
                                              (3.2, (0.62, 0.61, 0.58), 0.18),
                                              (400.0, (0.45, 0.44, 0.42), 0.20)),
                  walls=("buildings",), wall_gap=4.0, lamps=28.0, lane_width=(3.0, 3.5),
                  markings=("yellow_double_solid", "white_dashed", "white_solid"),
                  asphalt=(0.36, 0.36, 0.37)),
    "highway": dict(shoulder=(1.8, 3.0), verge=((0.8, (0.52, 0.50, 0.45), 0.25),
                                                (400.0, (0.30, 0.40, 0.18), 0.35)),
                    walls=("barrier", "trees"), wall_gap=0.3, lamps=45.0, lane_width=(3.5, 3.75),
                    markings=("yellow_solid", "white_dashed", "white_solid"),
                    asphalt=(0.33, 0.33, 0.34)),
    "rural": dict(shoulder=(0.3, 0.8), verge=((1.2, (0.50, 0.44, 0.34), 0.30),
                                              (400.0, (0.36, 0.46, 0.20), 0.40)),
                  walls=("trees",), wall_gap=8.0, lamps=0.0, lane_width=(3.0, 3.5),
                  markings=("yellow_dashed", "white_dashed", "white_solid"),
                  asphalt=(0.38, 0.37, 0.36)),
})
SCENE_KIND_NAMES = tuple(SCENE_KINDS)
