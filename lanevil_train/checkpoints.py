"""Reading checkpoint files safely, with errors that name the option that gave the file; writing them atomically.

Every option that takes a checkpoint (`ckpt_path`, `task.init_from`, `backbone.checkpoint`) reads it here.
Files are loaded with `torch.load(weights_only=True)`: tensors and plain values only, never arbitrary
pickled objects, since unpickling an untrusted file can run code. A file that is not a readable
checkpoint (random bytes, empty, truncated, or holding Python objects) is a `CheckpointError` saying what
is wrong with it; torch's own message is not passed on, because it advises loading the file unsafely.

Training writes its checkpoints through `AtomicCheckpointIO`: beside the final name, then renamed into place,
so a run killed while saving leaves the previous `last.ckpt` whole (Lightning's own writer stages the file in
the system temp folder, and moving it to an output folder on another file system is a copy a kill can cut).
"""

from __future__ import annotations

import io
import re
import zipfile
from pathlib import Path
from typing import Any

import pytorch_lightning as pl
from pytorch_lightning.plugins.io import TorchCheckpointIO

from lanevil_train.files.atomic import atomic_write_bytes, remove_temporaries

_UNSAFE_GLOBAL = re.compile(r"Unsupported global: GLOBAL ([\w.]+)")
_ZIP_MAGIC = b"PK\x03\x04"  # torch.save (since torch 1.6) writes a zip archive


class CheckpointError(ValueError):
    """A checkpoint option names a file that is not a readable checkpoint."""


def load_checkpoint_file(path: str | Path, option: str) -> object:
    """The object saved in `path` (on the CPU); `option` names where the path came from, e.g. "ckpt_path"."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{option}={path}: no such checkpoint file")
    if path.stat().st_size == 0:
        raise CheckpointError(f"{option}={path}: not a readable checkpoint: the file is empty (0 bytes)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - every failure becomes one clear message below
        raise CheckpointError(f"{option}={path}: not a readable checkpoint: {_reason(path, error)}") from None


def _reason(path: Path, error: Exception) -> str:
    """What is wrong with the file, in words: from its layout (torch.save writes a zip archive) and torch's error."""
    size = path.stat().st_size
    unsafe = _UNSAFE_GLOBAL.search(str(error))
    if unsafe:
        return (f"it holds a pickled Python object ({unsafe.group(1)}), and only tensors and plain values are "
                f"loaded from checkpoint files (unpickling objects can run code); save the weights as a state dict "
                f"(torch.save(model.state_dict(), path)) or a Lightning checkpoint")
    if is_truncated_archive(path):
        return (f"it is truncated ({size} bytes: it starts like a torch.save archive but its end is missing; an "
                f"interrupted save or copy leaves such a file)")
    if _starts_like_zip(path):
        return f"it is corrupt ({size} bytes: a zip archive whose content torch.load cannot read)"
    return f"its content is not a torch.save file ({size} bytes); expected a Lightning .ckpt or a torch.save file"


def _starts_like_zip(path: Path) -> bool:
    with open(path, "rb") as handle:
        return handle.read(4) == _ZIP_MAGIC


def is_truncated_archive(path: str | Path) -> bool:
    """Whether the file starts like a torch.save (zip) archive but its end, the zip directory, is missing: a save
    or a download that stopped."""
    return _starts_like_zip(Path(path)) and not zipfile.is_zipfile(path)


def read_lightning_checkpoint(path: str | Path, option: str) -> dict:
    """A Lightning checkpoint (a dict with a 'state_dict'), read safely; errors name `option` and the file."""
    return lightning_checkpoint(load_checkpoint_file(path, option), path, option)


def lightning_checkpoint(checkpoint: object, path: str | Path, option: str) -> dict:
    """The object read from `path`, checked to be a Lightning checkpoint (a dict with a 'state_dict')."""
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint:
        raise CheckpointError(f"{option}={path}: not a Lightning checkpoint (no 'state_dict'); expected a .ckpt "
                              f"file written by task=train (e.g. <run>/checkpoints/last.ckpt)")
    return checkpoint


# ---------------------------------------------------------------------------------------------- its kind

# Where task=train model=vlm/embedded builds the model it then fine-tunes, in its run folder: the base model folder its
# checkpoints name.
EMBEDDED_BASE_FOLDER = "init"


def vlm_base_model(checkpoint: dict) -> str | None:
    """The base model folder a VLM fine-tuning checkpoint names (its hyper_parameters' model_dir), else None."""
    hparams = checkpoint.get("hyper_parameters")
    return str(hparams["model_dir"]) if isinstance(hparams, dict) and hparams.get("model_dir") else None


def detector_name(checkpoint: dict) -> tuple[str, str] | None:
    """(family, backbone) of a lane detector's checkpoint, from the network spec task=train stores in it, else None."""
    try:
        spec = checkpoint["lanevil_model"]
        return str(spec["model"]["name"]), str(spec["backbone"]["name"])
    except (KeyError, TypeError):
        return None


def _model_type(model_dir: str) -> str:
    """The family (model_type) in a VLM folder's config.json, or "a model" when it cannot be read."""
    import json

    try:
        return str(json.loads((Path(model_dir) / "config.json").read_text())["model_type"])
    except (OSError, ValueError, KeyError, TypeError):
        return "a model"


def vlm_model_option(model_dir: str) -> str:
    """The `model=` a VLM checkpoint is used with: the embedded VLM's runs, or the Hugging Face folder it was tuned
    from."""
    if Path(model_dir).name == EMBEDDED_BASE_FOLDER:
        return "model=vlm/embedded"
    return f"model=vlm/hf model.path={model_dir}"


def check_detector_checkpoint(checkpoint: dict, where: str, spec: dict | None = None) -> None:
    """A lane detector's checkpoint, and, given this run's network spec, of its family and backbone; a VLM's
    checkpoint, or a detector of another family or backbone, is a CheckpointError starting with `where` that names the
    model= it needs (rather than counting weights that cannot fit)."""
    model_dir = vlm_base_model(checkpoint)
    if model_dir is not None:
        raise CheckpointError(f"{where}: a VLM's checkpoint ({_model_type(model_dir)} fine-tuned from {model_dir}), "
                              f"not a lane detector's; give it with {vlm_model_option(model_dir)}")
    saved = detector_name(checkpoint)
    wanted = (str(spec["model"]["name"]), str(spec["backbone"]["name"])) if spec else None
    if saved is not None and wanted is not None and saved != wanted:
        raise CheckpointError(f"{where}: a {saved[0]}-{saved[1]} checkpoint, and this run builds {wanted[0]}-"
                              f"{wanted[1]}; use model={saved[0]} backbone={saved[1]}")


def check_vlm_checkpoint(checkpoint: dict, where: str) -> str:
    """The base model folder of a VLM fine-tuning checkpoint; a lane detector's checkpoint (or any other) is a
    CheckpointError starting with `where` that says what it is and how it is used."""
    model_dir = vlm_base_model(checkpoint)
    if model_dir is not None:
        return model_dir
    name = detector_name(checkpoint)
    if name is None:
        raise CheckpointError(f"{where}: not a VLM fine-tuning checkpoint (its hyper_parameters name no model_dir); "
                              f"expected a checkpoint a task=train run of a model=vlm/<backend> wrote")
    raise CheckpointError(f"{where}: a lane detector's checkpoint ({name[0]}-{name[1]}), not a VLM's; drop "
                          f"model=vlm/...: detector tasks rebuild model={name[0]} backbone={name[1]} from it")


def load_weights(model, path: str | Path, option: str, checkpoint: object = None) -> dict:
    """Read the Lightning checkpoint at `path` (or check `checkpoint`, the object already read from it), check it is
    one of `model`'s family and backbone, and load its weights into `model`; returns the checkpoint."""
    checkpoint = read_lightning_checkpoint(path, option) if checkpoint is None else \
        lightning_checkpoint(checkpoint, path, option)
    check_detector_checkpoint(checkpoint, f"{option}={path}", getattr(model, "build_config", None))
    fit_weights(model, checkpoint["state_dict"], f"{option}={path}")
    return checkpoint


def fit_weights(model, state_dict: dict, where: str) -> None:
    """Load `state_dict` into `model`; weights of another network (model, backbone or input size) are an error
    starting with `where` that counts the missing, unexpected and differently shaped weights."""
    import torch

    own = model.state_dict()
    missing = [k for k in own if k not in state_dict]
    unexpected = [k for k in state_dict if k not in own]
    reshaped = [f"{k} {tuple(v.shape)} vs {tuple(own[k].shape)}" for k, v in state_dict.items()
                if k in own and isinstance(v, torch.Tensor) and v.shape != own[k].shape]
    if missing or unexpected or reshaped:
        parts = [f"{len(names)} {what} (first: {', '.join(names[:3])})"
                 for names, what in ((missing, "missing"), (unexpected, "unexpected"), (reshaped, "of another shape"))
                 if names]
        raise CheckpointError(f"{where}: its weights do not fit this run's network (model, backbone and input size "
                              f"must match the checkpoint's): weights {'; '.join(parts)}")
    model.load_state_dict(state_dict)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's torch checkpoint writer, made atomic on local paths: the file is written to a hidden `.partial`
    temporary beside its final name, fsynced and renamed, so it is at every instant the old file or the whole new
    one (remote URLs such as s3://... go through Lightning's own writer)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None or "://" in str(path):
            return super().save_checkpoint(checkpoint, path, storage_options)
        import torch

        buffer = io.BytesIO()
        torch.save(checkpoint, buffer)
        atomic_write_bytes(path, buffer.getbuffer())


def remove_stale_checkpoint_temporaries(callbacks: list) -> None:
    """Delete the `.partial` files a run killed while saving a checkpoint left in the checkpoint folders (nothing
    writes there before fit starts)."""
    for callback in callbacks:
        if isinstance(callback, pl.callbacks.ModelCheckpoint) and callback.dirpath and Path(callback.dirpath).is_dir():
            remove_temporaries(callback.dirpath)
