"""Progress display for long loops: a live bar on a terminal, plain periodic lines in logs and pipes.

Modes (the `progress=` option): auto (a bar when stdout is a terminal, else plain lines), rich, tqdm (bars),
plain (a line every `interval` seconds with the count, rate and ETA), none.
"""

from __future__ import annotations

import sys
import time

MODES = ("auto", "rich", "tqdm", "plain", "none")


def resolve_mode(mode: str) -> str:
    """The concrete display for `mode`: auto becomes rich on a terminal and plain otherwise."""
    if mode not in MODES:
        raise ValueError(f"progress={mode!r}: expected one of {', '.join(MODES)}")
    if mode == "auto":
        return "rich" if sys.stdout.isatty() else "plain"
    return mode


def duration(seconds: float) -> str:
    """Seconds as a short human duration: 42s, 7m01s, 2h05m."""
    seconds = max(0, int(round(seconds)))
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"


class PlainProgress:
    """Counts finished units and prints `desc: done/total (pct) | rate | ETA` at the first update (unless
    first_line=False), then every `interval` seconds, and at the end (unless last_line=False)."""

    def __init__(self, total: int, initial: int = 0, desc: str = "", unit: str = "it", interval: float = 30.0,
                 stream=None, first_line: bool = True, last_line: bool = True):
        self.total, self.done, self.desc, self.unit, self.interval = total, initial, desc, unit, interval
        self.stream = stream or sys.stdout
        self.start_count, self.start = initial, time.monotonic()
        self.last_print: float | None = None if first_line else self.start
        self.last_line = last_line

    def update(self, n: int = 1, note: str = "") -> None:
        """Count n more finished units; `note` (e.g. the current loss) goes into the line if one is printed."""
        self.done += n
        now = time.monotonic()
        if (self.last_print is None or now - self.last_print >= self.interval
                or (self.last_line and self.done >= self.total)):
            self.print_line(now, note)

    def print_line(self, now: float | None = None, note: str = "") -> None:
        now = time.monotonic() if now is None else now
        self.last_print = now
        elapsed = now - self.start
        rate = (self.done - self.start_count) / elapsed if elapsed > 0 else 0.0
        left = self.total - self.done
        eta = duration(left / rate) if rate > 0 and left > 0 else ("0s" if left <= 0 else "?")
        pct = f" ({100.0 * self.done / self.total:.0f}%)" if 0 < self.total < float("inf") else ""
        total = self.total if self.total < float("inf") else "?"
        parts = [f"{self.desc}: {self.done}/{total} {self.unit}{pct}", note, f"{rate:.2f} {self.unit}/s",
                 f"elapsed {duration(elapsed)}", f"ETA {eta}"]
        print(" | ".join(p for p in parts if p), file=self.stream, flush=True)

    def close(self) -> None:
        if self.last_print is None or self.done != self.total:
            self.print_line()


class _Silent:
    def update(self, n: int = 1, note: str = "") -> None:
        pass

    def close(self) -> None:
        pass


def progress_counter(total: int, initial: int = 0, desc: str = "", unit: str = "it", mode: str = "auto"):
    """An object with update(n) and close() showing the progress of `total` units in the display `mode` picks."""
    mode = resolve_mode(mode)
    if mode == "none":
        return _Silent()
    if mode == "plain":
        return PlainProgress(total, initial, desc, unit)
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit=unit, desc=desc)
