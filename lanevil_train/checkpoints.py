"""Reading checkpoint files safely, with errors that name the option that gave the file; writing them atomically.

Every option that takes a torch file (`ckpt_path`, `task.init_from`, `backbone.checkpoint`,
`model.head.anchor_frequency_file`, task.models' checkpoints) reads it here. Files are loaded with
`torch.load(weights_only=True)`: tensors and plain values only, never arbitrary pickled objects, since unpickling
an untrusted file can run code. A file that is not a readable checkpoint (random bytes, empty, truncated) is a
`CheckpointError` saying what is wrong with it; one holding pickled objects is named for what it is, with the
first objects its pickle imports (read with pickletools, files/pickles.py, not from torch's words, which change
between versions and advise loading the file unsafely). A release archive (a zip of checkpoints, as LaneATT
publishes its experiments) is read at its last epoch, or at the member `ARCHIVE::member` names.

Training writes its checkpoints through `AtomicCheckpointIO`: beside the final name, then renamed into place,
so a run killed while saving leaves the previous `last.ckpt` whole (Lightning's own writer stages the file in
the system temp folder, and moving it to an output folder on another file system is a copy a kill can cut).
"""

from __future__ import annotations

import io
import logging
import re
import zipfile
from pathlib import Path
from typing import Any

import pytorch_lightning as pl
from pytorch_lightning.plugins.io import TorchCheckpointIO

from lanevil_train.files.atomic import atomic_write_bytes, remove_temporaries
from lanevil_train.files.pickles import ZIP_MAGIC, objects_not_loaded

log = logging.getLogger(__name__)

# ckpt_path=release.zip::experiments/laneatt_r18_tusimple/models/model_0100.pt: one checkpoint inside an archive
ARCHIVE_MEMBER = "::"
CHECKPOINT_SUFFIXES = (".pt", ".pth", ".ckpt", ".bin", ".tar")
_EPOCH = re.compile(r"(\d+)\D*$")  # the last number of a file name: model_0100.pt -> 100


class CheckpointError(ValueError):
    """A checkpoint option names a file that is not a readable checkpoint."""


def archive_path(path: str | Path) -> Path:
    """The file a checkpoint option names: the archive of `ARCHIVE::member`, else the path itself."""
    return Path(str(path).split(ARCHIVE_MEMBER, 1)[0])


def load_checkpoint_file(path: str | Path, option: str) -> object:
    """The object saved in `path` (on the CPU); `option` names where the path came from, e.g. "ckpt_path".

    `path` may also be a release archive (a zip of checkpoints, as LaneATT publishes its experiments): its one
    experiment's last epoch is read, or the member `ARCHIVE::member` names; the log says which."""
    archive, _, member = str(path).partition(ARCHIVE_MEMBER)
    path = Path(archive)
    if not path.is_file():
        raise FileNotFoundError(f"{option}={path}: no such checkpoint file")
    if path.stat().st_size == 0:
        raise CheckpointError(f"{option}={path}: not a readable checkpoint: the file is empty (0 bytes)")
    if member or is_release_archive(path):
        member = _release_member(path, member, option)
        with zipfile.ZipFile(path) as release:
            return _load(release.read(member), f"{option}={path}{ARCHIVE_MEMBER}{member}")
    return _load(path, f"{option}={path}")


def _load(source: Path | bytes, where: str) -> object:
    """torch.load, weights-only, of a file or its bytes; a CheckpointError starting with `where` otherwise."""
    import torch

    try:
        return torch.load(source if isinstance(source, Path) else io.BytesIO(source), map_location="cpu",
                          weights_only=True)
    except Exception:  # noqa: BLE001 - said below in our words: torch's change between versions and advise
        pass           # loading the file unsafely
    objects = objects_not_loaded(source)
    if objects:
        shown = ", ".join(objects[:3]) + (f" and {len(objects) - 3} more" if len(objects) > 3 else "")
        raise CheckpointError(f"{where}: not a plain weights file: it holds pickled Python objects that weights-only "
                              f"loading will not run ({shown}); loading it any other way executes code from "
                              f"whoever made the file. Use a file of weights alone (torch.save(model.state_dict(), "
                              f"path)) or a Lightning checkpoint") from None
    raise CheckpointError(f"{where}: not a readable checkpoint: {_reason(source)}") from None


def _reason(source: Path | bytes) -> str:
    """What is wrong with a file torch.load cannot read, in words, from its layout (torch.save writes a zip)."""
    size = len(source) if isinstance(source, bytes) else source.stat().st_size
    if not _starts_like_zip(source):
        return f"its content is not a torch.save file ({size} bytes); expected a Lightning .ckpt or a torch.save file"
    if not zipfile.is_zipfile(io.BytesIO(source) if isinstance(source, bytes) else source):
        return (f"it is truncated ({size} bytes: it starts like a torch.save archive but its end is missing; an "
                f"interrupted save or copy leaves such a file)")
    return f"it is corrupt ({size} bytes: a zip archive whose content torch.load cannot read)"


def _starts_like_zip(source: Path | bytes) -> bool:
    if isinstance(source, bytes):
        return source[:4] == ZIP_MAGIC
    with open(source, "rb") as handle:
        return handle.read(4) == ZIP_MAGIC


def is_truncated_archive(path: str | Path) -> bool:
    """Whether the file starts like a torch.save (zip) archive but its end, the zip directory, is missing: a save
    or a download that stopped."""
    return _starts_like_zip(Path(path)) and not zipfile.is_zipfile(path)


def is_release_archive(path: Path) -> bool:
    """A zip archive that is not itself a torch.save file (whose pickle is <folder>/data.pkl beside its tensors)."""
    if not path.is_file() or not _starts_like_zip(path) or not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
    return not any(n.count("/") == 1 and n.endswith("/data.pkl") for n in names)


def _release_member(path: Path, member: str, option: str) -> str:
    """The checkpoint to read in the release archive `path`: `member` (its name, or the end of it), else its one
    experiment's last epoch; a CheckpointError naming what is inside and what to give otherwise."""
    with zipfile.ZipFile(path) as archive:
        names = [n for n in archive.namelist() if not n.endswith("/")]
    checkpoints = [n for n in names if n.endswith(CHECKPOINT_SUFFIXES)]
    where = f"{option}={path}"
    if member:
        found = [n for n in names if n == member] or [n for n in names if n.endswith("/" + member.lstrip("/"))]
        if len(found) == 1:
            log.info("%s: a release archive; reading %s, as named", where, found[0])
            return found[0]
        what = (f"{len(found)} members end with it ({', '.join(found[:4])})" if found else
                f"no member of that name; its checkpoints: {_listing(checkpoints or names)}")
        raise CheckpointError(f"{where}{ARCHIVE_MEMBER}{member}: {what}")
    if not checkpoints:
        raise CheckpointError(f"{where}: a zip archive that is neither a torch.save file nor a release holding "
                              f"checkpoints ({', '.join(CHECKPOINT_SUFFIXES)}); it holds {_listing(names)}")
    experiments = sorted({_experiment(n) for n in checkpoints})
    if len(experiments) > 1:
        raise CheckpointError(f"{where}: a release archive of {len(experiments)} experiments "
                              f"({', '.join(experiments[:6])}{', ...' if len(experiments) > 6 else ''}); name the "
                              f"checkpoint to read: {option}={path}{ARCHIVE_MEMBER}{_last_epoch(checkpoints)}")
    chosen = _last_epoch(checkpoints)
    log.info("%s: a release archive (%s); reading %s, the last of its %d checkpoint%s (another: %s%s<member>)",
             where, experiments[0] or "one experiment", chosen, len(checkpoints), "s" * (len(checkpoints) > 1),
             where, ARCHIVE_MEMBER)
    return chosen


def _experiment(name: str) -> str:
    """The experiment a checkpoint member belongs to: its folder, above a models/ or checkpoints/ folder."""
    folder = name.rpartition("/")[0]
    head, _, last = folder.rpartition("/")
    return head if last in ("models", "checkpoints") else folder


def _last_epoch(names: list[str]) -> str:
    """The member with the largest number at the end of its file name (model_0100.pt), the last name otherwise."""
    def epoch(name: str) -> int:
        match = _EPOCH.search(name.rpartition("/")[2].rsplit(".", 1)[0])
        return int(match.group(1)) if match else -1
    return max(sorted(names), key=epoch)


def _listing(names: list[str]) -> str:
    return f"{', '.join(names[:5])}{', ...' if len(names) > 5 else ''} ({len(names)} files)"


# ---------------------------------------------------------------------------------------------- its layout

# Where checkpoint files keep their weights: the official repositories' 'model' and 'net', Lightning's and mmcv's
# 'state_dict', plain PyTorch training scripts' 'model_state_dict'; or the file is the state dict itself.
WEIGHT_KEYS = ("model", "net", "state_dict", "model_state_dict")
DETECTOR_LAYOUTS = ("a Lightning checkpoint ('state_dict', as task=train writes), an official repository's file "
                    "(weights under 'model', 'net' or mmcv's 'state_dict'), a plain PyTorch script's "
                    "{'model_state_dict': ...}, or a bare state dict (torch.save(model.state_dict(), path))")


def is_state_dict(obj: object) -> bool:
    """A non-empty dict of tensors."""
    import torch

    return isinstance(obj, dict) and bool(obj) and all(isinstance(v, torch.Tensor) for v in obj.values())


def weights_in(obj: object) -> dict | None:
    """The state dict a checkpoint holds: under the first of WEIGHT_KEYS that holds a dict, or the object itself;
    None when that is no state dict."""
    if not isinstance(obj, dict):
        return None
    state = next((obj[key] for key in WEIGHT_KEYS if isinstance(obj.get(key), dict)), obj)
    return dict(state) if is_state_dict(state) else None


def what_it_holds(obj: object) -> str:
    """A checkpoint object in words: a dict by its top-level keys, anything else by its type."""
    if isinstance(obj, dict):
        keys = list(obj)
        return (f"a dict whose top-level keys are {', '.join(map(str, keys[:8]))}{', ...' if len(keys) > 8 else ''}"
                if keys else "an empty dict")
    shape = getattr(obj, "shape", None)
    return f"a {type(obj).__name__}" + (f" of shape {tuple(shape)}" if shape is not None else "")


def read_lightning_checkpoint(path: str | Path, option: str) -> dict:
    """A Lightning checkpoint (a dict with a 'state_dict'), read safely; errors name `option` and the file."""
    return lightning_checkpoint(load_checkpoint_file(path, option), path, option)


def lightning_checkpoint(checkpoint: object, path: str | Path, option: str) -> dict:
    """The object read from `path`, checked to be a Lightning checkpoint (a dict with a 'state_dict')."""
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint:
        raise CheckpointError(f"{option}={path}: {what_it_holds(checkpoint)}, not a Lightning checkpoint (no "
                              f"'state_dict'); expected a .ckpt file written by task=train (e.g. "
                              f"<run>/checkpoints/last.ckpt)")
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
