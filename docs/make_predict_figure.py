"""Draw docs/predict.png: what `task=predict task.illusion=...` writes for a video, two frames of a drive down a
simulated road (the first, and one a second later), each clean | with the illusion, a detector's lanes drawn on both.

Usage: python docs/make_predict_figure.py --ckpt outputs/train/<date>/checkpoints/last.ckpt [--out docs/predict.png]
       [--illusion fence_shadow] [--severity 4] [--seed 11]
The checkpoint is a trained `experiment=quickstart` LaneATT (an untrained model draws no meaningful lanes). The
video (1280x720, 10 fps, 50 km/h) is written into a temporary folder and run through the same code as task=predict
(lanevil_train.predict.predict_source), the illusion's ground recovered from the model's own clean lanes.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from lanevil_train import load_detector
from lanevil_train.predict import IllusionSettings, PredictSettings, open_source, predict_source
from lanevil_train.sim import build_scene, sample_scene_params, scene_at, shade_scene

FPS = 10.0
FRAMES = 11  # 1 s of driving
SHOWN = (0, 10)  # the frames in the figure


def write_drive(path: Path, seed: int) -> None:
    """A straight three-lane highway at noon, driven at 50 km/h."""
    params = sample_scene_params(seed).replace(road="straight", weather="clear_noon", scene_kind="highway", num_lanes=3)
    road = build_scene(seed, params, 1280, 720)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (1280, 720))
    for k in range(FRAMES):
        writer.write(cv2.cvtColor(shade_scene(scene_at(road, k * 50 / 3.6 / FPS)), cv2.COLOR_RGB2BGR))
    writer.release()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True, help="a trained experiment=quickstart checkpoint (last.ckpt)")
    parser.add_argument("--out", default=str(Path(__file__).with_name("predict.png")))
    parser.add_argument("--illusion", default="fence_shadow")
    parser.add_argument("--severity", type=int, default=4)
    parser.add_argument("--seed", type=int, default=11, help="the simulated road's seed")
    args = parser.parse_args()

    detector = load_detector(args.ckpt).eval()
    with tempfile.TemporaryDirectory() as work:
        video = Path(work) / "drive.mp4"
        write_drive(video, args.seed)
        settings = PredictSettings(progress="none", illusion=IllusionSettings(args.illusion, args.severity))
        summary = predict_source(detector, open_source(video), Path(work) / "out", settings)
        frames = [cv2.imread(str(Path(summary["frames"]) / f"frame_{k:06d}.jpg")) for k in SHOWN]
    sheet = np.concatenate(frames, axis=0)
    sheet = cv2.resize(sheet, (sheet.shape[1] // 2, sheet.shape[0] // 2), interpolation=cv2.INTER_AREA)
    cv2.imwrite(args.out, sheet)
    print(f"wrote {args.out}: {summary['illusion']}; timing {summary['timing']}")


if __name__ == "__main__":
    main()
