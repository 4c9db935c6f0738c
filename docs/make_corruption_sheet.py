"""Write docs/corruptions.png: one simulated scene (320x180) under each of the 11 non-illusion corruptions at severities
1, 3 and 5 (a row per corruption), and the six combined-illusion pairs of a combined-suite case at severity 4; the
sheet is halved for its file size.

Usage: python docs/make_corruption_sheet.py [--out docs/corruptions.png] [--seed 1000003]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from lanevil_train.corruptions import CORRUPTION_NAMES, CORRUPTIONS
from lanevil_train.data.illusion_set import Plan, case_source, synthetic_cases
from lanevil_train.perturbations import combined_choice, get_perturbation, suite_names
from lanevil_train.taxonomy import pair_label

SIZE = (180, 320)  # (H, W) of a cell
SEVERITIES = (1, 3, 5)


def caption(image: np.ndarray, text: str) -> np.ndarray:
    """A copy with a small white-on-black caption in its top-left corner."""
    out = np.ascontiguousarray(image).copy()
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
    cv2.rectangle(out, (0, 0), (tw + 6, th + base + 4), (0, 0, 0), -1)
    cv2.putText(out, text, (3, th + 2), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/corruptions.png")
    parser.add_argument("--seed", type=int, default=1000003)
    args = parser.parse_args()
    case = synthetic_cases(1, args.seed)[0]
    clean, _, ctx = case_source(case, Plan(illusions=(), size=SIZE))
    rows = [[caption(clean, "original")] + [caption(CORRUPTIONS[name](clean, None, s, args.seed), f"{name} s{s}")
                                           for s in SEVERITIES] for name in CORRUPTION_NAMES]
    _, pairs = combined_choice(args.seed, suite_names("combined"))
    cells = [caption(get_perturbation(p)(clean, ctx, 4, args.seed),
                     f"{pair_label(get_perturbation(p).category)}: {p.replace('+', ' + ')}") for p in pairs]
    blank = np.zeros_like(clean)
    cells += [blank] * (-len(cells) % 4)
    rows += [cells[i:i + 4] for i in range(0, len(cells), 4)]
    sheet = np.concatenate([np.concatenate(row, axis=1) for row in rows], axis=0)
    sheet = cv2.resize(sheet, (sheet.shape[1] // 2, sheet.shape[0] // 2), interpolation=cv2.INTER_AREA)  # file size
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"{args.out}: {sheet.shape[1]}x{sheet.shape[0]}")


if __name__ == "__main__":
    main()
