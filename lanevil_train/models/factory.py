"""The detector factory, in plain Python: a typed spec of a network, the network it builds, and loading one from a
file (this project's checkpoints and the official files models/official.py recognises).

    from lanevil_train import load_detector
    det = load_detector("last.ckpt")              # or an official file: load_detector("tusimple_18.pth")
    lanes = det.predict(cv2.imread("frame.jpg"))  # [PredictedLane(points, score), ...] in the image's own pixels

``DetectorSpec`` is what a model's build config records (the ``lanevil_model`` entry of every checkpoint; the
``model`` and ``backbone`` config groups, ``data.input_size``, ``data.crop_top``, ``data.normalize``,
``data.resize``), typed and checked: the family's config (its head, neck, decoding, optimizer: ``conf/model/
<family>.yaml``), the backbone's, and the input geometry, whose ``preprocessor()`` (data/preprocessor.py) is the one
place an image becomes the network's input and its lanes come back. ``create_detector(spec)`` builds the network
(each ``_target_`` imported and called with its arguments; errors name the config key). ``load_detector(path)``
reads a file weights-only (checkpoints.py), builds the network its spec names and loads the weights; an official
file's spec is its release's ``experiment=official_<family>_<dataset>`` config (the one place this module composes a
Hydra config, since those settings live in the experiment files).
"""

from __future__ import annotations

import functools
import importlib
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from lanevil_train.data.normalization import DEFAULT_NORMALIZATION, NORMALIZATIONS
from lanevil_train.data.preprocessor import Preprocessor
from lanevil_train.data.resize import DEFAULT_RESIZE
from lanevil_train.errors import prefixed

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DetectorSpec:
    """A detector network: its family's config, its backbone's, and its input geometry and pixel conventions."""

    model: dict
    backbone: dict
    input_size: tuple[int, int]
    crop_top: float = 0.0
    normalize: str = DEFAULT_NORMALIZATION
    resize: str = DEFAULT_RESIZE
    extra: dict = field(default_factory=dict)  # other keys of a stored build config, kept as they are

    def __post_init__(self) -> None:
        for name in ("model", "backbone"):
            if not isinstance(getattr(self, name), Mapping):
                raise ValueError(f"{name}: expected a mapping (its config group), got "
                                 f"{type(getattr(self, name)).__name__}")
        if self.model.get("kind", "detector") != "detector":
            raise ValueError(f"model={self.model.get('name')}: a {self.model.get('kind')} model, not a lane detector")
        if not isinstance(self.model.get("head"), Mapping) or "_target_" not in self.model["head"]:
            raise ValueError("model.head: expected a mapping with a _target_ naming the family's head class")
        if "_target_" not in self.backbone:
            raise ValueError("backbone: expected a mapping with a _target_ (e.g. "
                             "lanevil_train.models.backbones.build_backbone)")
        if self.normalize not in NORMALIZATIONS:
            raise ValueError(f"normalize={self.normalize!r}: expected one of {', '.join(NORMALIZATIONS)}")
        preprocessor = self.preprocessor()  # checks the input size, crop, resize filter
        object.__setattr__(self, "input_size", preprocessor.input_size)
        object.__setattr__(self, "model", dict(self.model))
        object.__setattr__(self, "backbone", dict(self.backbone))

    @property
    def family(self) -> str:
        return str(self.model.get("name", ""))

    def preprocessor(self) -> Preprocessor:
        return Preprocessor(tuple(self.input_size), self.crop_top, self.normalize, self.resize)

    @classmethod
    def from_build_config(cls, config: Mapping) -> DetectorSpec:
        """The spec of a stored build config (tasks/builders.model_config; older ones lack normalize / resize)."""
        known = {"model", "backbone", "input_size", "crop_top", "normalize", "resize"}
        missing = [key for key in ("model", "backbone", "input_size") if key not in config]
        if missing:
            raise ValueError(f"a detector's build config needs {', '.join(missing)}; got keys {sorted(config)}")
        return cls(model=dict(config["model"]), backbone=dict(config["backbone"]),
                   input_size=tuple(config["input_size"]), crop_top=float(config.get("crop_top") or 0.0),
                   normalize=config.get("normalize") or DEFAULT_NORMALIZATION,
                   resize=config.get("resize") or DEFAULT_RESIZE,
                   extra={k: v for k, v in config.items() if k not in known})

    def build_config(self) -> dict:
        """The plain dict stored in checkpoints (from_build_config's inverse)."""
        return {**self.extra, "model": dict(self.model), "backbone": dict(self.backbone),
                "input_size": list(self.input_size), "crop_top": float(self.crop_top), "normalize": self.normalize,
                "resize": self.resize}


def build_target(node: Mapping, key: str, **kwargs):
    """Call the `_target_` of a config node with its other entries (and `kwargs`); ``_partial_: true`` gives a
    functools.partial instead. Nested nodes with a `_target_` are built first. Errors name `key`: its own message
    when it starts with the key already, "<key>.<argument>: ..." when it names one of the node's arguments, else
    "<key>: ..."."""
    if not isinstance(node, Mapping) or "_target_" not in node:
        raise ValueError(f"{key}: expected a mapping with a _target_, got {node!r}")
    target = _import(str(node["_target_"]), key)
    arguments = {name: build_target(value, f"{key}.{name}") if isinstance(value, Mapping) and "_target_" in value
                 else value for name, value in node.items() if not str(name).startswith("_")}
    arguments.update(kwargs)
    if node.get("_partial_"):
        return functools.partial(target, **arguments)
    try:
        return target(**arguments)
    except Exception as error:  # noqa: BLE001 - every constructor error is the config's: name its key
        if str(error).startswith(key):
            raise
        argument = str(error).split(":", 1)[0]
        if argument in node:
            raise prefixed(error, key, sep=".") from error
        raise prefixed(error, key) from error


def _import(path: str, key: str):
    module, _, name = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError) as error:
        raise ValueError(f"{key}._target_: cannot import {path!r} ({error})") from None


def create_detector(spec: DetectorSpec):
    """The LaneDetector a spec describes, with random weights (or the backbone's local pretrained file when its
    config names one): the backbone stages the family reads (model.feature_strides, unless backbone.out_indices
    names them), dilated by model.output_stride; the neck, if any; the head built from the channels and strides of
    the maps it gets; the optimizer and schedule of the family's config."""
    from lanevil_train.models.backbones import indices_for_strides
    from lanevil_train.models.detector import LaneDetector

    model = spec.model
    backbone_node = dict(spec.backbone)
    output_stride = backbone_node.get("output_stride") or model.get("output_stride")
    if backbone_node.get("out_indices") is None:
        wanted = model.get("feature_strides") or [32]
        try:
            backbone_node["out_indices"] = list(indices_for_strides(backbone_node.get("name"), wanted, output_stride))
        except ValueError as error:
            raise ValueError(f"backbone={backbone_node.get('name')}: {error}") from None
    backbone_node["output_stride"] = output_stride
    backbone = build_target(backbone_node, "backbone")
    channels, strides = backbone.channels, backbone.strides
    neck = None
    if model.get("neck") is not None:
        neck = build_target(model["neck"], "model.neck", in_channels=channels, in_strides=strides)
        channels, strides = neck.channels, neck.strides
    head = build_target(model["head"], "model.head", in_channels=list(channels), in_strides=list(strides),
                        image_size=tuple(spec.input_size))
    optimizer, scheduler = _optimizer_and_schedule(model)
    detector = LaneDetector(backbone, head, neck=neck, optimizer=optimizer, scheduler=scheduler,
                            reference_batch_size=model.get("reference_batch_size"),
                            lr_scaling=model.get("lr_scaling", "none"), decode=model.get("decode"),
                            crop_top=spec.crop_top, lr_multipliers=model.get("lr_multipliers"),
                            gradient_clip_norm=model.get("gradient_clip_norm"),
                            row_sampling=model.get("row_sampling", "linear"), culane_rows=model.get("culane_rows"))
    detector.build_config = spec.build_config()
    return detector


def _optimizer_and_schedule(model: dict):
    """model.optimizer and model.scheduler as callables (their `_partial_` targets). Checkpoints written before
    these were targets hold {lr, weight_decay} (Adam) and "cosine" / "none"; they load as they trained."""
    optimizer = model.get("optimizer") or {}
    if "_target_" not in optimizer:
        optimizer = {"_target_": "lanevil_train.models.detector.adam", "_partial_": True, **optimizer}
    scheduler = model.get("scheduler", "cosine")
    if scheduler == "cosine":
        scheduler = {"_target_": "lanevil_train.models.schedules.cosine", "_partial_": True}
    elif scheduler == "none":
        scheduler = None
    return (build_target(optimizer, "model.optimizer"),
            None if scheduler is None else build_target(scheduler, "model.scheduler"))


def official_spec(config: str, overrides: list[str] | tuple[str, ...] = ()) -> DetectorSpec:
    """The spec of an official release's settings, e.g. "experiment=official_ufld_tusimple backbone=resnet18" (what
    models/official.py's recognition names for a file), composed from the package's config files."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    overrides = [*config.split(), "data.root=unused", *overrides]
    if GlobalHydra.instance().is_initialized():  # inside a Hydra run (a task): its own config search path
        cfg = compose(config_name="config", overrides=overrides)
    else:
        with initialize_config_module(config_module="lanevil_train.conf", version_base=None):
            cfg = compose(config_name="config", overrides=overrides)
    missing = sorted(f"model.{key}" for key in OmegaConf.missing_keys(cfg.model))
    if missing:
        raise ValueError(f"{config}: {', '.join(missing)} must be given (its files do not hold it), e.g. "
                         f"official_spec({config!r}, ['{missing[0]}=...'])")
    get = functools.partial(OmegaConf.to_container, resolve=True)
    return DetectorSpec(model=get(cfg.model), backbone=get(cfg.backbone), input_size=tuple(cfg.data.input_size),
                        crop_top=float(cfg.data.get("crop_top") or 0.0),
                        normalize=str(cfg.data.get("normalize") or DEFAULT_NORMALIZATION),
                        resize=str(cfg.data.get("resize") or DEFAULT_RESIZE))


def load_detector(path: str | Path, spec: DetectorSpec | None = None, device=None):
    """The detector of a file, with its weights, in eval mode on `device` (default the CPU):

    - this project's checkpoint (task=train's last.ckpt, or any Lightning checkpoint holding ``lanevil_model``): the
      network its stored spec describes (`spec`, when given, replaces it);
    - an official repository's file (models/official.py: UFLD, LaneATT, CLRNet, SCNN, BezierLaneNet, GANet): the
      network of the release it is recognised as (`spec`: another one, e.g. official_spec(...) with
      model.head.anchor_frequency_file=... for LaneATT, whose anchors are not in its files);
    - a bare state dict in this project's names: only with `spec`.
    Files are read weights-only; a LaneATT zip member as ``zip::member`` (checkpoints.py)."""
    return read_detector(path, spec).eval().to(device or "cpu")


def read_detector(path: str | Path, spec: DetectorSpec | None = None, default=None, where: str | None = None):
    """load_detector's network with its weights, as built (train mode, on the CPU). `default` (a DetectorSpec, or a
    function making one, called only when needed) is the spec of a file that names none of its own (an official
    file, a bare state dict, a checkpoint without its build config); `where` names the file in errors (e.g.
    "ckpt_path=last.ckpt")."""
    def fallback() -> DetectorSpec | None:
        return default() if callable(default) else default

    from lanevil_train.checkpoints import check_detector_checkpoint, fit_weights, load_checkpoint_file
    from lanevil_train.models.official import check_layout, load_official, official_state_dict, recognise

    where = where or str(path)
    checkpoint = load_checkpoint_file(path, where.split("=", 1)[0] if "=" in where else "path")
    official = official_state_dict(checkpoint)
    if official is not None:
        spec = spec or fallback()
        if spec is None:
            found = recognise(official)
            if found is None or not found[1].config.startswith("experiment="):
                raise ValueError(f"{where}: not a file of an official release this project recognises (nor this "
                                 f"project's checkpoint): pass spec=DetectorSpec(...) for a bare state dict")
            spec = official_spec(found[1].config)
        model = create_detector(spec)
        log.info(load_official(model, official, where))
        return model
    check_layout(checkpoint, where)
    check_detector_checkpoint(checkpoint, where)  # a VLM's names the model= it needs
    stored = checkpoint.get("lanevil_model")
    spec = spec or (DetectorSpec.from_build_config(stored) if stored else fallback())
    if spec is None:
        raise ValueError(f"{where}: a checkpoint without its build config ('lanevil_model'): pass spec=")
    model = create_detector(spec)
    fit_weights(model, checkpoint["state_dict"], where)
    return model
