"""Whole weight files: the safetensors (single or sharded) and torch `.bin` files of a saved model or adapter folder,
checked before anything loads them.

A file cut short (a download or copy that stopped) otherwise fails deep inside the loader with the safetensors
library's own "incomplete metadata", naming neither the folder nor the file. A safetensors file is an 8-byte
little-endian header length N, N bytes of JSON ({tensor name: {"dtype", "shape", "data_offsets": [begin, end]}},
offsets into the data that follows), then the data: the header alone says how long the whole file must be. A
sharded model lists its shards in `<weights>.index.json` ("weight_map": tensor name -> file); each must be there
and whole. A torch `.bin` file is a zip archive whose directory sits at its end (checkpoints.is_truncated_archive).
Only the headers are read: checking a model of many gigabytes takes milliseconds.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

WEIGHT_SUFFIXES = (".safetensors", ".bin")
INDEX_SUFFIX = ".index.json"


def safetensors_problem(path: Path) -> str | None:
    """What is wrong with a safetensors file ("truncated: ..."), or None when its size is what its header says."""
    size = path.stat().st_size
    if size < 8:
        return f"truncated: {size} bytes, shorter than the 8-byte header length a safetensors file starts with"
    with open(path, "rb") as handle:
        (header_bytes,) = struct.unpack("<Q", handle.read(8))
        if 8 + header_bytes > size:
            return f"truncated: header says its JSON alone takes {8 + header_bytes} bytes, file has {size}"
        try:
            header = json.loads(handle.read(header_bytes))
        except (UnicodeDecodeError, ValueError) as error:
            return f"corrupt: its header is not JSON ({error})"
    if not isinstance(header, dict):
        return f"corrupt: its header is a JSON {type(header).__name__}, expected an object of tensors"
    ends = [entry["data_offsets"][1] for name, entry in header.items()
            if name != "__metadata__" and isinstance(entry, dict) and len(entry.get("data_offsets") or ()) == 2]
    expected = 8 + header_bytes + max(ends, default=0)
    if size < expected:
        return f"truncated: header says {expected} bytes, file has {size}"
    return None


def _shards(index: Path, where: str) -> set[str]:
    """The file names a sharded checkpoint's index lists in its weight_map."""
    try:
        weight_map = json.loads(index.read_text(encoding="utf-8"))["weight_map"]
        return {str(name) for name in weight_map.values()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
        raise ValueError(f"{where}: {index.name} is not a shard index with a weight_map "
                         f"({type(error).__name__}: {error})") from None


def check_weight_files(folder: str | Path, option: str) -> None:
    """Every weight file in `folder` (a saved model or peft adapter) is whole, and every shard an index lists is there;
    else a ValueError naming the option that gave the folder, the folder, the file and what is wrong:
    "model.path /m: model-00002-of-00002.safetensors is truncated: header says N bytes, file has M"."""
    from lanevil_train.checkpoints import is_truncated_archive

    folder = Path(folder)
    where = f"{option} {folder}"
    files = {p.name for p in folder.iterdir() if p.is_file() and p.name.endswith(WEIGHT_SUFFIXES)}
    for index in sorted(folder.glob(f"*{INDEX_SUFFIX}")):
        for shard in sorted(_shards(index, where)):
            if not (folder / shard).is_file():
                raise FileNotFoundError(f"{where}: {shard}, a shard {index.name} lists, is missing; expected every "
                                        f"shard of a sharded checkpoint beside its index")
            files.add(shard)
    for name in sorted(files):
        path = folder / name
        if name.endswith(".safetensors"):
            problem = safetensors_problem(path)
        else:
            problem = (f"truncated: {path.stat().st_size} bytes, a torch archive whose end is missing"
                       if is_truncated_archive(path) else None)
        if problem is not None:
            raise ValueError(f"{where}: {name} is {problem} (a download or copy that stopped?); fetch or save "
                             f"it again")
