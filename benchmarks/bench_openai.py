"""OpenAI-compatible backend throughput: requests/s against the local fake server at several concurrencies.

Each request carries one clip of 6 frames (360x640 by default, road-like synthetic images: smooth shading, lane
lines, mild noise) as PNG or JPEG data URLs plus a question; the server (a separate process, --no-decode) adds
--delay-ms of latency per request, as a remote model would. Clips are asked `--questions-per-clip` questions each,
as in the suite (5 QA per clip), so each clip's frames are encoded once per batch.

Usage: python benchmarks/bench_openai.py [--concurrency 1 8 32] [--formats png jpeg] [--delay-ms 50]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

# lanevil_dev (the test doubles of a source checkout, not in the wheel) is imported from the checkout root
CHECKOUT = Path(__file__).resolve().parents[1]
if str(CHECKOUT) not in sys.path:
    sys.path.insert(0, str(CHECKOUT))


def road_frame(seed: int, height: int, width: int) -> np.ndarray:
    """A road-like RGB frame: sky and asphalt gradients, two lane lines, mild noise."""
    rng = np.random.default_rng(seed)
    rows = np.linspace(0.0, 1.0, height)[:, None, None]
    sky = np.array([150, 190, 235]) * (1 - 0.3 * rows)
    road = np.array([90, 90, 95]) * (0.8 + 0.4 * rows)
    image = np.where(rows < 0.45, sky, road) * np.ones((1, width, 1))
    cols = np.arange(width)[None, :]
    for offset in (-0.35, 0.35):
        x = width / 2 + offset * width * (np.arange(height)[:, None] / height - 0.45) / 0.55
        line = (np.abs(cols - x) < 3) & (np.arange(height)[:, None] > 0.45 * height)
        image[line] = 235
    image += rng.normal(0, 3, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


def run(concurrency: int, image_format: str, requests: int, questions_per_clip: int, url: str,
        frames: tuple[int, int]) -> dict:
    """Time `requests` requests at `concurrency`; requests/s and the payload size."""
    from lanevil_train.vlm.backends.openai import OpenAIVLM, encode_frame

    clips_needed = -(-requests // questions_per_clip)
    clips = [[road_frame(100 * c + f, *frames) for f in range(6)] for c in range(clips_needed)]
    clips = [clips[i // questions_per_clip] for i in range(requests)]
    questions = [f"Question {i}: how many lanes are there?" for i in range(requests)]
    vlm = OpenAIVLM(url, "fake-vlm", concurrency=concurrency, image_format=image_format, backoff_s=0.1)
    vlm.answer(clips[:concurrency], questions[:concurrency])  # warm the connections
    start = time.perf_counter()
    for begin in range(0, requests, vlm.batch_size):  # as the evaluation loop hands batches over
        vlm.answer(clips[begin:begin + vlm.batch_size], questions[begin:begin + vlm.batch_size])
    seconds = time.perf_counter() - start
    payload = sum(len(encode_frame(f, image_format)) for f in clips[0])
    vlm.client.close()
    return {"format": image_format, "concurrency": concurrency, "requests": requests,
            "seconds": round(seconds, 2), "requests_per_s": round(requests / seconds, 1),
            "payload_kib_per_request": round(payload / 1024)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--concurrency", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--formats", nargs="+", default=["png", "jpeg"], choices=["png", "jpeg"])
    parser.add_argument("--delay-ms", type=float, default=50.0)
    parser.add_argument("--seconds", type=float, default=8.0, help="aim per setting (sets the request count)")
    parser.add_argument("--questions-per-clip", type=int, default=5)
    parser.add_argument("--size", type=int, nargs=2, default=[360, 640], metavar=("HEIGHT", "WIDTH"))
    args = parser.parse_args()
    from lanevil_dev.fake_server import FakeServer

    with FakeServer("--delay-ms", str(args.delay_ms), "--no-decode", idle_exit_s=120) as server:
        for image_format in args.formats:
            for concurrency in args.concurrency:
                ideal = concurrency * 1000 / max(args.delay_ms, 1.0)  # latency-bound requests/s
                requests = max(2 * concurrency, min(int(args.seconds * ideal), 2000))
                result = run(concurrency, image_format, requests, args.questions_per_clip, server.url,
                             tuple(args.size))
                result["latency_bound_requests_per_s"] = round(ideal, 1)
                print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
