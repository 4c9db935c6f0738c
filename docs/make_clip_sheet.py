"""Write docs/clips.png: VLM benchmark clips as a person sees them. For a few cases (one illusion each), the three
segments (before / over / alongside) as rows of 6 frames, clean above and the illusion at severity 5 below, each
row labelled; and the clip's QA in docs/clips_qa.md.

Usage: python docs/make_clip_sheet.py [--cases rail_shadow road_crack vehicle] [--size 108x192]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from lanevil_train.taxonomy import ILLUSION_NAMES
from lanevil_train.vlm.clips.clips import SEGMENTS, ClipCase, clip_cases, clip_truth, render_clip
from lanevil_train.vlm.clips.suite_qa import suite_qa

DOCS = Path(__file__).resolve().parent
SUITE_CASES = 100


def labelled_row(frames: list[np.ndarray], label: str, gap: int = 4) -> np.ndarray:
    """The frames side by side, with the label written on the first one."""
    height, width = frames[0].shape[:2]
    row = np.full((height, len(frames) * (width + gap) - gap, 3), 255, np.uint8)
    for k, frame in enumerate(frames):
        row[:, k * (width + gap): k * (width + gap) + width] = frame
    cv2.rectangle(row, (0, 0), (min(row.shape[1], 9 * len(label) + 8), 20), (0, 0, 0), -1)
    cv2.putText(row, label, (4, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["rail_shadow", "road_crack", "vehicle"])
    parser.add_argument("--first-seed", type=int, default=1000000)
    parser.add_argument("--size", default="108x192", help="frame HxW")
    parser.add_argument("--out", type=Path, default=DOCS / "clips.png")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    rows, qa_lines = [], ["# QA of the clips in clips.png", "",
                          f"Planned as the first cases of a suite of {SUITE_CASES} (vlm/clips/suite_qa.py: a closed "
                          f"question is asked only where its suite answers it both ways).", ""]
    cases = [ClipCase(f"clip-{args.first_seed + i}", args.first_seed + i, illusion)
             for i, illusion in enumerate(args.cases)]
    suite = cases + clip_cases(SUITE_CASES - len(cases), args.first_seed + len(cases), list(ILLUSION_NAMES))
    planned = suite_qa([(f"{case.case_id}-{segment}", case.seed, clip_truth(case, segment, size=size))
                        for case in suite for segment in SEGMENTS])
    for case in cases:
        illusion = case.illusion
        for segment in SEGMENTS:
            frames = render_clip(case, segment, [0, 5], size=size)
            rows.append(labelled_row(frames[0], f"{illusion} {segment}: clean"))
            rows.append(labelled_row(frames[5], f"{illusion} {segment}: severity 5"))
            rows.append(np.full((8, rows[-1].shape[1], 3), 255, np.uint8))
            qa_lines.append(f"## {illusion}, {segment}")
            qa_lines.append("")
            for qa in planned[f"{case.case_id}-{segment}"]:
                choices = f" ({' / '.join(qa['choices'])})" if qa["type"] == "choice" else ""
                qa_lines.append(f"- *{qa['category']}, {qa['type']}*: {qa['question']}{choices} — **{qa['answer']}**")
            qa_lines.append("")
    sheet = np.concatenate(rows, axis=0)
    cv2.imwrite(str(args.out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    (args.out.parent / "clips_qa.md").write_text("\n".join(qa_lines))
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]}) and {args.out.parent / 'clips_qa.md'}")


if __name__ == "__main__":
    main()
