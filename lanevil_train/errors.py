"""Re-raising an error with the input it concerns named in front (a label file:line, a config key, a case)."""

from __future__ import annotations


def prefixed(error: BaseException, prefix: str, sep: str = ": ") -> Exception:
    """`error` re-made as "<prefix><sep><message>": of the same type where that type takes one message, else of the
    first of FileNotFoundError, ValueError, TypeError it is, else a RuntimeError. Raise it `from` the original."""
    message = f"{prefix}{sep}{error}"
    bases = [kind for kind in (FileNotFoundError, ValueError, TypeError) if isinstance(error, kind)][:1]
    for kind in (type(error), *bases):
        try:
            remade = kind(message)
        except Exception:  # noqa: BLE001 - a type whose constructor takes other arguments: try its base
            continue
        if str(remade) == message:
            return remade
    return RuntimeError(message)
