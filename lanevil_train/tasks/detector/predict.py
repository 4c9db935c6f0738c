"""task=predict: a detector over your own images and videos, lanes drawn on every frame, an annotated video, the
lanes of every frame in per_frame.jsonl (resumable) and the official prediction files. The work is plain Python
(lanevil_train/predict/: the frame sources, the drawing, the run); this reads the config and loads the model.

    python -m lanevil_train task=predict ckpt_path=last.ckpt task.input=dashcam/            # a folder, recursively
    python -m lanevil_train task=predict ckpt_path=last.ckpt task.input=drive.mp4 task.out_dir=out/drive
    python -m lanevil_train task=predict experiment=official_clrnet_culane ckpt_path=culane_r18.pth task.input=a.jpg
    python -m lanevil_train task=predict ckpt_path=last.ckpt task.input=drive.mp4 task.illusion=rail_shadow
"""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from lanevil_train.errors import prefixed
from lanevil_train.models.head import check_decode_options
from lanevil_train.predict.illusion import IllusionSettings, read_labels
from lanevil_train.predict.run import FRAMES_DIR, PredictSettings, predict_source
from lanevil_train.predict.sources import open_source
from lanevil_train.tasks.builders import checkpoint_model, inference_device, output_dir

log = logging.getLogger(__name__)


def predict(cfg: DictConfig) -> float:
    """Predict on task.input with ckpt_path's detector into task.out_dir (default: the run directory); returns
    the frames per second of the frames predicted in this run (network, reading, drawing and writing)."""
    if not cfg.ckpt_path:
        raise ValueError("task=predict needs ckpt_path=CHECKPOINT: a task=train checkpoint (last.ckpt), or a published "
                         "file with its experiment=official_<family>_<dataset>")
    if not cfg.task.input:
        raise ValueError("task.input: task=predict needs an image, a folder of images, a video or a list file (.txt): "
                         "task.input=PATH")
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    try:  # the input is checked before the model loads: a list's missing image, a video with no frames
        source = open_source(cfg.task.input, cfg.task.stride, cfg.task.max_frames, exclude=out / FRAMES_DIR)
    except (OSError, ValueError) as error:
        raise prefixed(error, f"task.input={cfg.task.input}") from None
    illusion, labels = None, {}
    if cfg.task.illusion:
        illusion = IllusionSettings(str(cfg.task.illusion), int(cfg.task.severity), int(cfg.task.seed),
                                    float(cfg.task.speed_kmh), float(cfg.task.relayout_m), float(cfg.task.smoothing))
        if cfg.task.labels:  # read and checked whole before the model loads
            root = source.path if source.path.is_dir() else source.path.parent
            labels = read_labels(cfg.task.labels, root)
    elif cfg.task.labels:
        raise ValueError(f"task.labels={cfg.task.labels}: labels give the ground of an illusion; set "
                         "task.illusion=NAME too (or leave task.labels out)")
    settings = PredictSettings(batch_size=int(cfg.task.batch_size), format=str(cfg.task.format),
                               progress=str(cfg.progress), write_frames=bool(cfg.task.write_frames),
                               jpeg_quality=int(cfg.task.jpeg_quality), illusion=illusion)
    model = checkpoint_model(cfg)
    overrides = {key: value for key, value in OmegaConf.to_container(cfg.task.decode, resolve=True).items()
                 if value is not None}
    check_decode_options(model.head, overrides, "task.decode")
    model.decode_kwargs.update(overrides)
    model = model.eval().to(inference_device(cfg))
    log.info("task=predict: %s (%s, %s frames) with %s on %s", source.path, source.kind,
             source.total if source.total is not None else "?", cfg.ckpt_path, inference_device(cfg))
    summary = predict_source(model, source, out, settings, labels)
    return summary["frames_per_s"]
