"""Checkpoints the official repositories publish, loaded as they were saved.

A file given as ``ckpt_path`` (task=evaluate, export, closed_loop) or ``task.init_from`` (fine-tuning, e.g. with
AAM++) may be an official checkpoint instead of one of ours: it is read weights-only (tensors and plain values,
never pickled code), its weights are found in the repository's layout (``{"model": ...}``, ``{"net": ...}``, a bare
state dict; ``module.`` prefixes of DataParallel dropped), its release recognised from its keys and shapes by the
families' ``official.py`` modules (``RELEASES``), converted to this project's names and loaded strictly into the
network the run's config builds (``experiment=official_<family>_<dataset>``). A file of another family or release
is refused naming what it is, the first weight that does not fit and the config that would; a file of a release
whose network no config of this project computes (e.g. pytorch-auto-drive's SCNN on a ResNet) is refused saying
why.

A family supports its published weights with one module, ``models/<family>/official.py``, holding a ``RELEASE``
(``models/release.py``: its model name, how to recognise, check and convert a file, its optional training-only
parts), listed in ``_releases`` below.
"""

from __future__ import annotations

from pathlib import Path

import torch

from lanevil_train.checkpoints import (
    DETECTOR_LAYOUTS,
    CheckpointError,
    fit_weights,
    load_checkpoint_file,
    load_weights,
    weights_in,
    what_it_holds,
)
from lanevil_train.models.bezierlanenet.official import RELEASE as BEZIERLANENET
from lanevil_train.models.clrernet.official import RELEASE as CLRERNET
from lanevil_train.models.clrnet.official import RELEASE as CLRNET
from lanevil_train.models.ganet.official import RELEASE as GANET
from lanevil_train.models.laneatt.official import RELEASE as LANEATT
from lanevil_train.models.release import Recognised, Release
from lanevil_train.models.scnn.official import RELEASE as SCNN
from lanevil_train.models.ufld.official import RELEASE as UFLD

__all__ = ["Recognised", "Release", "load_detector_weights", "load_official", "official_state_dict", "recognise"]

DDP_PREFIX = "module."


def _releases() -> list[Release]:
    return [BEZIERLANENET, CLRERNET, CLRNET, GANET, LANEATT, SCNN, UFLD]


def is_ours(obj: object) -> bool:
    """A checkpoint written by this project (a Lightning checkpoint, with its 'state_dict')."""
    return isinstance(obj, dict) and "state_dict" in obj and ("lanevil_model" in obj or "pytorch-lightning_version"
                                                              in obj or "hyper_parameters" in obj)


def official_state_dict(obj: object) -> dict[str, torch.Tensor] | None:
    """The weights of a file that is not one of this project's checkpoints (an official repository's layout, a plain
    script's 'model_state_dict', a bare state dict: checkpoints.weights_in), 'module.' prefixes dropped; None when
    it holds none. A dict with a 'state_dict' is an official file (mmcv's layout) only when a release recognises its
    weights: otherwise it is taken for one of this project's checkpoints (whose own checks then say what does not
    fit)."""
    if not isinstance(obj, dict) or is_ours(obj):
        return None
    state = weights_in(obj)
    if state is None:
        return None
    state = {(k[len(DDP_PREFIX):] if k.startswith(DDP_PREFIX) else k): v for k, v in state.items()}
    if "state_dict" in obj and recognise(state) is None:
        return None
    return state


def recognise(state: dict) -> tuple[Release, Recognised] | None:
    """The release a state dict belongs to, with what it is, or None."""
    for release in _releases():
        found = release.describe(state)
        if found is not None:
            return release, found
    return None


def _first_weight(state: dict) -> str:
    key = next(iter(state))
    return f"{key} {tuple(state[key].shape)}"


def load_official(model, state: dict, where: str) -> str:
    """Convert an official state dict and load it into `model` (strictly); returns the one line to log. Weights of no
    release in this network's own names (a plain `torch.save(model.state_dict())`) load as they are. Refuses a file
    of no known release, of another family than the model's, or whose shapes do not fit this network."""
    known = ", ".join(release.name for release in _releases())
    found = recognise(state)
    if found is None and state.keys() & model.state_dict().keys():  # weights in this project's own names
        fit_weights(model, state, where)
        return f"{where}: a state dict of this network ({len(state)} tensors in its own names)"
    if found is None:
        raise CheckpointError(f"{where}: neither a checkpoint of this project (no 'state_dict') nor an official one "
                              f"of a release it reads ({known}); its first weight is {_first_weight(state)}")
    release, recognised = found
    if recognised.unsupported:
        raise CheckpointError(f"{where}: an official {release.name} checkpoint ({recognised.what}) that this project "
                              f"cannot load: {recognised.unsupported}")
    spec = getattr(model, "build_config", None) or {}
    family = str(spec.get("model", {}).get("name", ""))
    if family != release.family:
        own = next((r for r in _releases() if r.family == family), None)
        difference = None if own is None else own.difference(state)
        why = "" if difference is None else f" (not an official {own.name} file: {difference})"
        raise CheckpointError(f"{where}: an official {release.name} checkpoint ({recognised.what}), and this run "
                              f"builds model={family}{why}; run it with {recognised.config}")
    needed = release.missing_setting(model) or release.check(model, state)
    if needed:
        raise CheckpointError(f"{where}: an official {release.name} checkpoint ({recognised.what}); {needed}")
    converted = _fit_optional(release.convert(state), model.state_dict(), release.optional)
    try:
        fit_weights(model, converted, where)
    except CheckpointError as error:
        raise CheckpointError(f"{error}; the file is an official {release.name} checkpoint ({recognised.what}): "
                              f"{_advice(recognised, spec)}") from None
    return (f"{where}: official {release.name} checkpoint ({recognised.what}), {len(converted)} tensors "
            f"converted to this network's names")


def _advice(recognised: Recognised, spec: dict) -> str:
    """What to run a file whose shapes do not fit this run's network with: its release's settings; and where this
    run already has that release's family and backbone (it may be running those very settings), that a setting
    given on top of them changes the network, since the release's own network fits the file."""
    advice = f"run it with {recognised.config}, whose network has its shapes"
    backbone = str(spec.get("backbone", {}).get("name", ""))
    if recognised.config.startswith("experiment=") and f"backbone={backbone}" in recognised.config.split():
        advice += ("; if this run is that already, a setting given on top of it (data.input_size, data.max_lanes, "
                   "model.head.*) changes the network: drop it")
    return advice


def _fit_optional(converted: dict, own: dict, optional: tuple[str, ...]) -> dict:
    """`converted` with the optional parts made to fit the network: dropped where it has none, its own initial
    values where the file has none."""
    if not optional:
        return converted
    out = {k: v for k, v in converted.items() if k in own or not k.startswith(optional)}
    out.update({k: v for k, v in own.items() if k.startswith(optional) and k not in out})
    return out


def load_detector_weights(model, path: str | Path, option: str) -> str | None:
    """Load the weights of `path` into `model`: a checkpoint of this project (checked to be of the model's family
    and backbone) or an official one (converted); returns the log line of an official file, else None."""
    obj = load_checkpoint_file(path, option)
    state = official_state_dict(obj)
    if state is not None:
        return load_official(model, state, f"{option}={path}")
    check_layout(obj, f"{option}={path}")
    load_weights(model, path, option, checkpoint=obj)
    return None


def check_layout(obj: object, where: str) -> None:
    """A CheckpointError naming what the file holds unless it is one of this project's checkpoints (a dict with a
    'state_dict'): called where official_state_dict found no weights in the other layouts."""
    if not (isinstance(obj, dict) and "state_dict" in obj):
        raise CheckpointError(f"{where}: {what_it_holds(obj)}: none of the checkpoint layouts this project reads "
                              f"({DETECTOR_LAYOUTS})")
