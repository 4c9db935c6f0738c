"""What the pickles of a torch.save file import, read without unpickling anything (the standard library's
`pickletools` walks the opcodes), so that a file weights-only loading refuses can be named for what it holds
whatever torch's own message says.

A torch.save file is a zip archive (torch >= 1.6) whose one pickle is ``<folder>/data.pkl`` (its tensors' bytes are
other members), or the legacy format: five pickles one after another (magic number, protocol, system info, the
object, the storage keys) and then the storages' raw bytes. A pickle imports a global with the GLOBAL or INST
opcode (module and name in the opcode) or STACK_GLOBAL (module and name the two strings pushed just before it, or
fetched from the memo); the pickler writes nothing else between them, and frames and memo writes are skipped here.
"""

from __future__ import annotations

import io
import pickletools
import zipfile
from pathlib import Path
from typing import BinaryIO

ZIP_MAGIC = b"PK\x03\x04"
LEGACY_PICKLES = 5
_STRING_OPCODES = {"SHORT_BINUNICODE", "BINUNICODE", "BINUNICODE8", "UNICODE", "STRING", "BINSTRING",
                   "SHORT_BINSTRING"}
_MEMO_WRITES = {"PUT", "BINPUT", "LONG_BINPUT"}
_MEMO_READS = {"GET", "BINGET", "LONG_BINGET"}
_NO_PUSH = {"FRAME", "PROTO", "MEMOIZE", "STOP", *_MEMO_WRITES}

# What weights-only loading rebuilds besides tensors (torch.load(weights_only=True) allows these by default)
_PLAIN = {"_codecs.encode", "builtins.bytearray", "builtins.complex", "builtins.set", "builtins.frozenset",
          "builtins.slice", "collections.Counter", "collections.OrderedDict", "torch.serialization._get_layout"}
_TORCH_MODULES = {"torch._utils", "torch._tensor", "torch.nn.parameter", "torch.cuda", "torch.sparse",
                  "torch.cuda.sparse"}


def _globals_of_one_pickle(stream: BinaryIO) -> list[str]:
    """The module.name of each global one pickle imports, in order (stops at its STOP opcode)."""
    found, pushed, memo = [], [], {}
    for opcode, arg, _ in pickletools.genops(stream):
        name = opcode.name
        if name in ("GLOBAL", "INST"):
            found.append(".".join(str(arg).split(" ", 1)))
        elif name == "STACK_GLOBAL":
            module, attribute = pushed[-2:] if len(pushed) >= 2 else (None, None)
            found.append(f"{module}.{attribute}" if isinstance(module, str) and isinstance(attribute, str)
                         else "a global whose name is computed")
        if name == "MEMOIZE":
            memo[len(memo)] = pushed[-1] if pushed else None
        elif name in _MEMO_WRITES:
            memo[arg] = pushed[-1] if pushed else None
        elif name in _MEMO_READS:
            pushed.append(memo.get(arg))
        elif name in _STRING_OPCODES:
            pushed.append(arg if isinstance(arg, str) else bytes(arg).decode("latin-1"))
        elif name not in _NO_PUSH:
            pushed.append(None)
    return found


def pickled_globals(source: str | Path | bytes) -> list[str]:
    """Every global the pickles of a torch.save file (a path, or its bytes) import, each once, in order; [] when it
    holds no pickle that can be read."""
    handle = io.BytesIO(source) if isinstance(source, bytes) else open(source, "rb")
    found = []
    with handle:
        if handle.read(4) == ZIP_MAGIC:
            handle.seek(0)
            try:
                with zipfile.ZipFile(handle) as archive:
                    pickles = [n for n in archive.namelist() if n == "data.pkl" or n.endswith("/data.pkl")]
                    streams = [io.BytesIO(archive.read(n)) for n in pickles[:1]]
            except (zipfile.BadZipFile, OSError, EOFError):
                return []
        else:
            handle.seek(0)
            streams = [handle] * LEGACY_PICKLES  # read one after another from the same file
        for stream in streams:
            try:
                found += _globals_of_one_pickle(stream)
            except Exception:  # noqa: BLE001 - not a pickle (any more): the storages' raw bytes, or damage
                break
    return list(dict.fromkeys(found))


def _torch_plain(name: str) -> bool:
    import torch

    module, _, attribute = name.rpartition(".")
    if module in _TORCH_MODULES:
        return True
    if module != "torch":
        return False
    value = getattr(torch, attribute, None)  # a tensor or storage type, a dtype, Size, device, a qscheme
    return isinstance(value, (type, torch.dtype)) or type(value).__name__ == "qscheme"


def _user_allowed() -> set[str]:
    """The globals added with torch.serialization.add_safe_globals (torch >= 2.4), by name."""
    import torch.serialization as serialization

    names = set()
    for entry in getattr(serialization, "get_safe_globals", lambda: [])():
        if isinstance(entry, tuple):
            names.add(str(entry[1]))
        else:
            names.add(f"{getattr(entry, '__module__', '')}.{getattr(entry, '__qualname__', '')}")
    return names


def objects_not_loaded(source: str | Path | bytes) -> list[str]:
    """The globals of the file's pickles that weights-only loading will not run: anything but tensors, storages,
    dtypes and the plain containers (and what the user allowed with add_safe_globals)."""
    allowed = _user_allowed()
    return [name for name in pickled_globals(source)
            if name not in _PLAIN and name not in allowed and not _torch_plain(name)]
