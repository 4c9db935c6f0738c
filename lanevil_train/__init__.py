"""lanevil_train: robustness of lane perception to environmental illusions (LanEvil++).

The Python API, without Hydra (imported on first use, so `import lanevil_train` stays light):

    from lanevil_train import load_detector, apply_illusion
    det = load_detector("last.ckpt")           # this project's checkpoint, or an official file (models/factory.py)
    image = cv2.imread("frame.jpg")[:, :, ::-1]  # RGB
    lanes = det.predict(image, color="rgb")    # PredictedLane(points, score) in the image's own pixels
    seen = apply_illusion(image, [lane.points for lane in lanes], "rail_shadow", severity=3)
"""

__version__ = "0.1.0"

_API = {
    "load_detector": "lanevil_train.models.factory",
    "create_detector": "lanevil_train.models.factory",
    "DetectorSpec": "lanevil_train.models.factory",
    "official_spec": "lanevil_train.models.factory",
    "PredictedLane": "lanevil_train.models.detector",
    "Preprocessor": "lanevil_train.data.preprocessor",
    "apply_illusion": "lanevil_train.illusions.api",
}
__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        import importlib

        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module 'lanevil_train' has no attribute {name!r}")
