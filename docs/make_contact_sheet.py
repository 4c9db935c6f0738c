"""Write docs/contact_sheet.png: a 4x6 grid of rendered scenes covering roads, markings, weathers and
scene kinds, each labelled; the last row also shows the ground-truth lanes overlaid (green).

Usage: python docs/make_contact_sheet.py [--out docs/contact_sheet.png] [--thumb 320x180]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from lanevil_train.sim import SceneParams, render_scene

# (seed, params, overlay GT?) for each cell, row by row
CELLS = [
    (1, dict(road="straight", weather="clear_noon", scene_kind="urban"), False),
    (2, dict(road="left_curve", weather="clear_noon", scene_kind="highway", num_lanes=4,
             curvature=1 / 250), False),
    (3, dict(road="right_curve", weather="cloudy_noon", scene_kind="rural", num_lanes=2,
             markings=("yellow_dashed", "white_dashed", "white_solid"), curvature=1 / 200), False),
    (4, dict(road="s_curve", weather="clear_noon", scene_kind="rural", curvature=1 / 220), False),
    (5, dict(road="uphill", weather="cloudy_noon", scene_kind="urban", grade=0.08), False),
    (6, dict(road="downhill", weather="clear_noon", scene_kind="highway", grade=0.07, slope_start=30), False),
    (7, dict(weather="wet_noon", scene_kind="urban", num_lanes=4), False),
    (8, dict(weather="soft_rain_noon", scene_kind="highway", num_lanes=3, road="right_curve"), False),
    (9, dict(weather="sunset", scene_kind="highway", num_lanes=4, road="left_curve"), False),
    (10, dict(weather="night", scene_kind="urban", num_lanes=3), False),
    (11, dict(weather="night", scene_kind="highway", num_lanes=4, road="right_curve"), False),
    (12, dict(weather="sunset", scene_kind="rural", num_lanes=2, road="s_curve"), False),
    (13, dict(markings=("white_solid", "white_double_solid", "white_solid_dashed", "white_solid"),
              scene_kind="highway", num_lanes=3), False),
    (14, dict(markings=("yellow_double_solid", "botts_dots", "botts_dots", "white_solid"),
              scene_kind="urban", num_lanes=3, weather="cloudy_noon"), False),
    (15, dict(markings=("yellow_solid_dashed", "white_dashed", "yellow_solid"), num_lanes=2,
              scene_kind="rural"), False),
    (16, dict(markings=("yellow_solid", "white_dashed", "white_dashed", "white_dashed", "white_dashed",
                        "white_solid"), num_lanes=5, scene_kind="highway", weather="wet_noon"), False),
    (17, dict(paint_wear=0.8, scene_kind="urban", weather="clear_noon", road="left_curve"), False),
    (18, dict(ego_lane=0, lateral_offset=0.5, yaw_deg=4.0, scene_kind="highway", weather="cloudy_noon"), False),
    (19, None, True), (20, None, True), (21, None, True), (22, None, True), (23, None, True), (24, None, True),
]


def label(img: np.ndarray, text: str) -> None:
    """Small white-on-black caption in the top-left corner (in place)."""
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.36, 1)
    cv2.rectangle(img, (0, 0), (tw + 6, th + base + 4), (0, 0, 0), -1)
    cv2.putText(img, text, (3, th + 2), cv2.FONT_HERSHEY_SIMPLEX, 0.36, (255, 255, 255), 1, cv2.LINE_AA)


def cell_image(seed: int, spec: dict | None, overlay: bool, tw: int, th: int) -> np.ndarray:
    """One labelled thumbnail (rendered at 2x and downscaled for smooth edges)."""
    params = None if spec is None else SceneParams(**spec)
    sample = render_scene(seed, params, width=2 * tw, height=2 * th)
    img = np.ascontiguousarray(sample["image"])
    if overlay:
        for lane in sample["lanes"]:
            pts = np.round(lane * 4).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(img, [pts], False, (0, 255, 0), 1, cv2.LINE_AA, 2)
    img = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)
    meta = sample["meta"]
    marks = sorted(set(meta["markings"]))
    text = f"{meta['road']} {meta['weather']} {meta['scene_kind']} {meta['num_lanes']}L"
    label(img, text + (" GT" if overlay else ""))
    cap = ",".join(m.replace("white", "w").replace("yellow", "y").replace("_", "") for m in marks)
    (cw, ch), _ = cv2.getTextSize(cap, cv2.FONT_HERSHEY_SIMPLEX, 0.3, 1)
    cv2.rectangle(img, (0, th - ch - 6), (cw + 6, th), (0, 0, 0), -1)
    cv2.putText(img, cap, (3, th - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).with_name("contact_sheet.png")))
    ap.add_argument("--thumb", default="320x180", help="thumbnail WxH")
    ap.add_argument("--cols", type=int, default=4)
    args = ap.parse_args()
    tw, th = (int(v) for v in args.thumb.split("x"))
    cells = [cell_image(seed, spec, ov, tw, th) for seed, spec, ov in CELLS]
    rows = [np.concatenate(cells[i:i + args.cols], axis=1) for i in range(0, len(cells), args.cols)]
    sheet = np.concatenate(rows, axis=0)
    cv2.imwrite(args.out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")


if __name__ == "__main__":
    main()
