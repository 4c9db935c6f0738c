"""Lanes on your own images and videos, in plain Python (task=predict is its command line: tasks/detector/predict.py).

- ``sources``: the frames of an image, a folder of images (recursively), a video or a list file, as (key, BGR image)
  pairs, each checked before any work (a missing list entry, a video with no frames); an unreadable image or frame
  is named in a warning and skipped, counted by the source.
- ``drawing``: predicted lanes drawn over an image (a fixed palette, one colour per lane, its score beside it).
- ``illusion``: an illusion on each frame's ground, recovered from its lanes (the clean prediction or labels); in a
  video it lies fixed on the road and slides toward the camera as the car drives.
- ``run``: a detector over a source, writing the drawn frames (clean | illusion with one), the annotated video,
  ``per_frame.jsonl`` (resumable) and the official prediction files.

    from lanevil_train import load_detector
    from lanevil_train.predict import open_source, predict_source
    summary = predict_source(load_detector("last.ckpt"), open_source("drive.mp4"), "out/")
    summary = predict_source(detector, open_source("drive.mp4"), "out/",
                             PredictSettings(illusion=IllusionSettings("rail_shadow", severity=4)))
"""

from lanevil_train.predict.drawing import PALETTE, draw_lanes
from lanevil_train.predict.illusion import IllusionSettings, RoadIllusion
from lanevil_train.predict.run import PredictSettings, predict_source
from lanevil_train.predict.sources import IMAGE_EXTENSIONS, FrameSource, ImageSource, VideoSource, open_source

__all__ = ["IMAGE_EXTENSIONS", "PALETTE", "FrameSource", "IllusionSettings", "ImageSource", "PredictSettings",
           "RoadIllusion", "VideoSource",
           "draw_lanes", "open_source", "predict_source"]
