"""task=predict's pipeline against the network alone, on a 1280x720 video (issue 46; benchmarks/RESULTS.md
"task=predict throughput").

    python benchmarks/bench_predict.py --out /tmp/bench_predict [--frames 100] [--rounds 4] \
        [--setup laneatt model=laneatt] [--setup clrnet-paper experiment=paper_clrnet data.root=unused]

Per setup (a name and the config overrides that build the detector, random weights), in paired rounds: the forward
pass over the video's frames (preprocessed beforehand, batches of 8), the forward and its decoding, then
``predict_source`` (what task=predict runs: reading, preprocessing, the network, drawing, JPEGs, the annotated video,
per_frame.jsonl); the ratio pipeline / forward of each round cancels a shared machine's slow load changes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import time
from pathlib import Path

SETUPS = {"laneatt": ["model=laneatt"], "clrnet": ["model=clrnet"],
          "laneatt-paper": ["experiment=paper_laneatt", "data.root=unused"],
          "clrnet-paper": ["experiment=paper_clrnet", "data.root=unused"]}


def write_video(path: Path, frames: int) -> Path:
    """`frames` simulated 1280x720 road frames along one scene's road, as an mp4v video at 30 fps."""
    import cv2

    from lanevil_train.sim import render_scene

    if path.is_file():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (1280, 720))
    for k in range(frames):
        writer.write(render_scene(1000 + k % 8, width=1280, height=720)["image"][:, :, ::-1].copy())
    writer.release()
    return path


def detector(overrides: list[str]):
    from hydra import compose, initialize_config_module

    from lanevil_train.models.factory import DetectorSpec, create_detector
    from lanevil_train.tasks.builders import model_config

    with initialize_config_module(config_module="lanevil_train.conf", version_base=None):
        cfg = compose(config_name="config", overrides=list(overrides))
    return create_detector(DetectorSpec.from_build_config(model_config(cfg))).eval()


def network_seconds(det, frames, decode: bool) -> float:
    import torch

    batches = [det.preprocessor.batch(frames[i:i + 8]) for i in range(0, len(frames), 8)]
    with torch.inference_mode():
        det(batches[0])
        start = time.perf_counter()
        for x in batches:
            raw = det(x)
            if decode:
                det.head.decode(raw, **det.decode_kwargs, with_scores=True)
    return time.perf_counter() - start


def main() -> None:
    import cv2
    import torch

    from lanevil_train.predict import PredictSettings, open_source, predict_source

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--setup", nargs="+", action="append", metavar=("NAME", "OVERRIDE"),
                        help="a name and its overrides (repeatable; default: " + ", ".join(SETUPS) + ")")
    args = parser.parse_args()
    setups = {s[0]: s[1:] for s in args.setup} if args.setup else SETUPS
    video = write_video(args.out / "road_720p.mp4", args.frames)
    capture, frames = cv2.VideoCapture(str(video)), []
    while (frame := capture.read())[0]:
        frames.append(frame[1])
    results = {}
    for name, overrides in setups.items():
        torch.manual_seed(0)
        det = detector(overrides)
        rounds = []
        for _ in range(args.rounds):
            forward = network_seconds(det, frames, decode=False)
            decoded = network_seconds(det, frames, decode=True)
            out = args.out / name
            shutil.rmtree(out, ignore_errors=True)
            summary = predict_source(det, open_source(video), out, PredictSettings(progress="none"))
            rounds.append({"forward_fps": len(frames) / forward, "decode_fps": len(frames) / decoded,
                           "pipeline_fps": summary["predicted"] / summary["seconds"],
                           "ratio": summary["seconds"] / forward})
        results[name] = {"input_size": det.build_config["input_size"],
                         **{k: round(statistics.median(r[k] for r in rounds), 2) for k in rounds[0]}}
        print(name, results[name], flush=True)
    (args.out / "bench_predict.json").write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
