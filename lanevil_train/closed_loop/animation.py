"""An animated view of a run beside its clean twin: the camera images re-rendered from the traces' poses.

Each frame shows the two camera views side by side (illusion run left, clean twin right), captioned with the time
since entering the illusion region and the lateral deviation; a red dot marks the point the controller steered to
(its pure-pursuit target, from the trace), and a bar under each view the deviation against the ASR threshold (red
ticks). Written as a GIF (Pillow), atomically.
"""

from __future__ import annotations

import io
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from lanevil_train.closed_loop.episode import Run, render_view
from lanevil_train.closed_loop.run_scores import ASR_THRESHOLD_M
from lanevil_train.files.atomic import atomic_write_bytes
from lanevil_train.sim.vehicle import VehicleState

VIEW_WIDTH = 320
BAR_HEIGHT = 14
HEADER_HEIGHT = 20


def _view(run: Run, step: dict, size: tuple[int, int], entry_s: float | None) -> np.ndarray:
    state = VehicleState(s=step["s"], d=step["d"], heading=step["heading"], t=step["t"])
    image, posed = render_view(run, state, size)
    target = step.get("target")
    if target is not None:  # where the controller steers to: a point on the ground in the car's frame
        mount = replace(posed.camera, yaw_deg=posed.camera.yaw_deg - math.degrees(step["heading"]))
        u, v = mount.project(np.array([target[0], 0.0, target[1]]))
        if np.isfinite(u) and np.isfinite(v):
            cv2.circle(image, (int(round(u)), int(round(v))), max(3, image.shape[1] // 120), (255, 40, 40), -1)
    height = int(round(image.shape[0] * VIEW_WIDTH / image.shape[1]))
    image = cv2.resize(image, (VIEW_WIDTH, height), interpolation=cv2.INTER_AREA)
    header = np.zeros((HEADER_HEIGHT, VIEW_WIDTH, 3), np.uint8)
    since = "" if entry_s is None else f"  {step['t'] - entry_s:+.1f} s"
    text = f"{run.illusion if run.severity else 'clean'}{since}  dev {step['deviation']:+.2f} m"
    cv2.putText(header, text, (4, HEADER_HEIGHT - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    bar = np.full((BAR_HEIGHT, VIEW_WIDTH, 3), 30, np.uint8)
    centre, scale = VIEW_WIDTH // 2, VIEW_WIDTH / 4.0  # 2 m either side fills the bar
    for sign in (-1, 1):
        bar[:, int(centre + sign * ASR_THRESHOLD_M * scale)] = (255, 80, 80)
    x = int(np.clip(centre + step["deviation"] * scale, 2, VIEW_WIDTH - 3))
    over = abs(step["deviation"]) > ASR_THRESHOLD_M
    bar[2:-2, x - 2:x + 3] = (255, 60, 60) if over else (80, 220, 80)
    return np.vstack([header, image, bar])


def write_animation(pairs: list[tuple[Run, list[dict], float | None]], size: tuple[int, int], path: str | Path,
                    fps: float = 10.0) -> Path:
    """A GIF of the runs side by side, frame k of each trace together (a shorter trace holds its last frame):
    `pairs` is [(run, its trace, its entry time or None), ...]."""
    from PIL import Image

    if not pairs:
        raise ValueError("write_animation: no runs to animate")
    length = max(len(trace) for _, trace, _ in pairs)
    frames = []
    for k in range(length):
        views = [_view(run, trace[min(k, len(trace) - 1)], size, entry) for run, trace, entry in pairs]
        frames.append(Image.fromarray(np.hstack(views)))
    buffer = io.BytesIO()
    frames[0].save(buffer, format="GIF", save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    path = Path(path)
    atomic_write_bytes(path, buffer.getvalue())
    return path
