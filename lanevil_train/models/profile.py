"""What a network costs: parameters, FLOPs per image, latency and throughput at batch 1 and batch N, forward only and
forward + decode, and peak memory, on one device. Plain Python (no Hydra): functions taking a model and an input
size; `task=profile` (tasks/detector/profile.py) builds the models and writes the table.

FLOPs come from torch's own counter, `torch.utils.flop_counter.FlopCounterMode` (a maintained part of torch, no other
dependency), under its convention: a multiply-add is 2 FLOPs (a convolution or matrix product of M multiply-adds
counts 2M; a bias is not counted), and only the operations it has a formula for are counted (convolutions, matrix
products, attention), not element-wise operations, pooling, normalisation or sampling. Operations of extensions
(e.g. torchvision's deformable convolution) it cannot know are listed as uncounted. Papers that quote "GFLOPs"
counted as fvcore does (one per multiply-add) quote GMACs: half of the FLOPs here.

    from lanevil_train.models.profile import profile_network
    row = profile_network(model, (320, 800), torch.device("cpu"), batch_sizes=(1, 8), warmup=2, runs=5)
"""

from __future__ import annotations

import ctypes
import math
import resource
import statistics
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

FLOP_COUNTER = "torch.utils.flop_counter.FlopCounterMode"
FLOP_CONVENTION = ("a multiply-add counts 2 FLOPs (torch's flop counter; GMACs = GFLOPs / 2), bias additions, "
                   "element-wise operations, pooling, normalisation and sampling not counted")

Decode = Callable[[object, tuple[int, int], int], object]  # (raw outputs, input size, batch) -> decoded lanes


def count_parameters(model: nn.Module) -> dict[str, int]:
    """{"total": sum of p.numel(), "trainable": the same over the parameters that require a gradient} (a parameter
    shared by two modules is counted once, as model.parameters() yields it once)."""
    parameters = list(model.parameters())
    return {"total": sum(p.numel() for p in parameters),
            "trainable": sum(p.numel() for p in parameters if p.requires_grad)}


class _Operations(TorchDispatchMode):
    """The operations a forward runs (their overload packets, counted)."""

    def __init__(self):
        super().__init__()
        self.seen: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.seen[func._overloadpacket] += 1
        return func(*args, **(kwargs or {}))


def count_flops(model: nn.Module, input_size: tuple[int, int], device: torch.device | str = "cpu",
                image: torch.Tensor | None = None) -> dict:
    """FLOPs of one forward of `model` on one 3 x H x W image (FlopCounterMode's count: FLOP_CONVENTION).

    Returns {"flops": int, "macs": flops / 2, "by_part": {child module: flops} (the model's direct children, e.g.
    backbone, neck, head), "uncounted": [names of the extension operations (outside torch's aten) the forward ran
    that the counter has no formula for]}."""
    images = _batch(image, input_size, 1, device)
    operations = _Operations()
    counter = FlopCounterMode(display=False)
    # the counter's module tracker hooks the gradients of module inputs that require one, which a parameter passed to
    # a submodule does (a query embedding) and which no_grad cannot give: the parameters are frozen while it counts
    trainable = [p for p in model.parameters() if p.requires_grad]
    try:
        for p in trainable:
            p.requires_grad_(False)
        with torch.no_grad(), counter, operations:
            model(images)
    finally:
        for p in trainable:
            p.requires_grad_(True)
    total = int(counter.get_total_flops())
    by_module = counter.get_flop_counts()
    root = type(model).__name__
    by_part = {name: int(sum(by_module.get(f"{root}.{name}", {}).values())) for name, _ in model.named_children()}
    uncounted = sorted({str(op) for op in operations.seen
                        if op not in counter.flop_registry and not str(op).startswith("aten.")})
    return {"flops": total, "macs": total / 2, "by_part": {k: v for k, v in by_part.items() if v},
            "uncounted": uncounted}


def _batch(image: torch.Tensor | None, input_size: tuple[int, int], batch: int, device) -> torch.Tensor:
    """`image` (3 x H x W) repeated `batch` times, or a fixed random batch, on `device`."""
    height, width = input_size
    if image is None:
        image = torch.randn(3, height, width, generator=torch.Generator().manual_seed(0))
    if tuple(image.shape) != (3, height, width):
        raise ValueError(f"image: expected a 3 x {height} x {width} tensor (the input size), got {tuple(image.shape)}")
    return image.to(device=device, dtype=torch.float32).unsqueeze(0).repeat(batch, 1, 1, 1).contiguous()


def _synchronizer(device: torch.device) -> Callable[[], None]:
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def time_call(fn: Callable[[], object], warmup: int, runs: int, sync: Callable[[], None] = lambda: None) -> dict:
    """`fn` called `warmup` times untimed, then `runs` times, each timed alone (sync() before the clock stops: the
    device's queue drained); {"median_ms", "min_ms", "max_ms", "runs"}."""
    if runs < 1 or warmup < 0:
        raise ValueError(f"runs: expected >= 1 and warmup >= 0, got runs={runs}, warmup={warmup}")
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(runs):
        started = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - started) * 1e3)
    return {"median_ms": statistics.median(times), "min_ms": min(times), "max_ms": max(times), "runs": runs}


# --------------------------------------------------------------------------------------------------- peak memory

def _status_kib(field: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def _reset_peak_rss() -> bool:
    """Reset the process's peak RSS (Linux: VmHWM, by writing 5 to /proc/self/clear_refs); whether it could."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return _status_kib("VmHWM") is not None


def _release_freed_memory() -> None:
    """Hand memory freed by earlier runs back to the system (glibc's malloc_trim), so that a run's allocations show
    as growth of the resident size instead of reusing what a bigger run left."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except (OSError, AttributeError):
            pass


CUDA_MEMORY = "torch.cuda.max_memory_allocated over the runs (weights, inputs, activations and decoding)"
RSS_MEMORY = ("the process's peak resident memory growth over the runs (Linux /proc/self/status VmHWM, reset through "
              "/proc/self/clear_refs, after glibc malloc_trim; the weights, already resident, not included)")
MAXRSS_MEMORY = ("the growth of resource.getrusage's ru_maxrss over the runs (a lower bound: the process's earlier "
                 "peak is not reset; the weights not included)")


class PeakMemory:
    """The peak memory of what runs inside `with PeakMemory(device) as peak:`; then peak.bytes and peak.method."""

    def __init__(self, device: torch.device):
        self.device = torch.device(device)
        self.bytes: int | None = None
        self.method = ""

    def __enter__(self) -> PeakMemory:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.method = CUDA_MEMORY
        else:
            _release_freed_memory()
            self._hwm = _reset_peak_rss()
            self.method = RSS_MEMORY if self._hwm else MAXRSS_MEMORY
            self._start_kib = _status_kib("VmRSS") if self._hwm else _maxrss_kib()
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.bytes = int(torch.cuda.max_memory_allocated(self.device))
        else:
            end = _status_kib("VmHWM") if self._hwm else _maxrss_kib()
            self.bytes = max(0, end - self._start_kib) * 1024


def _maxrss_kib() -> int:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak // 1024 if sys.platform == "darwin" else peak  # bytes on macOS, KiB on Linux


# ------------------------------------------------------------------------------------------------------ profile

def detector_decode(model: nn.Module) -> Decode | None:
    """A LaneDetector's decoding (its head's decode and the mapping to image pixels: decode_lanes) as a Decode, or
    None for a network without one."""
    if not callable(getattr(model, "decode_lanes", None)):
        return None
    return lambda raw, size, batch: model.decode_lanes(raw, size, [size] * batch)


def measure_batch(model: nn.Module, images: torch.Tensor, warmup: int, runs: int,
                  decode: Decode | None = None) -> dict:
    """Latency of `model` on `images` (one batch): the forward alone and, with `decode`, forward + decode, each
    `warmup` untimed calls then the median of `runs`; with the peak memory of all of it (PeakMemory)."""
    device = images.device
    sync = _synchronizer(device)
    batch, size = images.shape[0], tuple(images.shape[-2:])
    out = {"batch": batch}
    with torch.inference_mode(), PeakMemory(device) as peak:
        forward = time_call(lambda: model(images), warmup, runs, sync)
        out["forward_ms"] = forward["median_ms"]
        out["forward_ms_range"] = [forward["min_ms"], forward["max_ms"]]
        if decode is not None:
            both = time_call(lambda: decode(model(images), size, batch), warmup, runs, sync)
            out["forward_decode_ms"] = both["median_ms"]
            out["forward_decode_ms_range"] = [both["min_ms"], both["max_ms"]]
    out["forward_fps"] = batch * 1e3 / out["forward_ms"]
    if "forward_decode_ms" in out:
        out["forward_decode_fps"] = batch * 1e3 / out["forward_decode_ms"]
    out["peak_memory_bytes"] = peak.bytes
    out["peak_memory_method"] = peak.method
    return out


def profile_network(model: nn.Module, input_size: Sequence[int], device: torch.device | str = "cpu",
                    batch_sizes: Sequence[int] = (1, 8), warmup: int = 2, runs: int = 5,
                    decode: Decode | None = None, image: torch.Tensor | None = None) -> dict:
    """Everything profile measures of `model` at `input_size` (H, W) on `device`: parameters (count_parameters),
    FLOPs per image (count_flops), and for each batch size the forward's and forward + decode's median latency and
    images/s and the peak memory (measure_batch). `decode` defaults to a LaneDetector's (detector_decode); `image`
    (3 x H x W, normalised as the network expects) is the input, repeated to each batch (default: fixed noise).
    The model is put in eval mode on `device`."""
    device = torch.device(device)
    size = (int(input_size[0]), int(input_size[1]))
    model = model.eval().to(device)
    decode = decode if decode is not None else detector_decode(model)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    row = {"input_size": list(size), "device": describe_device(device),
           "parameters": count_parameters(model), **count_flops(model, size, device, image),
           "flop_counter": f"{FLOP_COUNTER} (torch {torch.__version__})", "flop_convention": FLOP_CONVENTION,
           "warmup": warmup, "runs": runs, "batches": []}
    for batch in batch_sizes:
        row["batches"].append(measure_batch(model, _batch(image, size, int(batch), device), warmup, runs, decode))
    return row


def describe_device(device: torch.device) -> str:
    """The device in words: the GPU's name, or the CPU with the threads torch uses."""
    device = torch.device(device)
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (cuda:{device.index or 0})"
    return f"cpu ({torch.get_num_threads()} torch threads)"


# ------------------------------------------------------------------------------------------------------- table

def _count(n: float | None, unit: str = "M", scale: float = 1e6) -> str:
    if n is None:
        return "—"
    return f"{n / scale:,.2f} {unit}" if unit else f"{n / scale:,.2f}"


def _ms(value: float | None) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:,.1f}" if value >= 10 else f"{value:,.2f}"


def _fps(value: float | None) -> str:
    return "—" if value is None else f"{value:,.0f}" if value >= 10 else f"{value:,.2f}"


def _memory(value: int | None) -> str:
    if value is None:
        return "—"
    return f"{value / 2**30:,.2f} GiB" if value >= 2**30 else f"{value / 2**20:,.0f} MiB"


def markdown_table(rows: Sequence[dict]) -> str:
    """The rows of profile_network (each with a "label"; a failed one with an "error") as one markdown table: per
    batch size the forward's and forward + decode's median latency (ms) and images/s, and the peak memory."""
    batch_sizes = sorted({b["batch"] for row in rows for b in row.get("batches", [])})
    head = ["model", "input", "parameters (trainable)", "GFLOPs / image", "GMACs / image"]
    for n in batch_sizes:
        head += [f"batch {n}: forward ms", f"batch {n}: forward img/s", f"batch {n}: forward + decode ms",
                 f"batch {n}: forward + decode img/s", f"batch {n}: peak memory"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        label = row.get("label", "model")
        if "error" in row:
            lines.append("| " + " | ".join([label, f"failed: {row['error']}"] + [""] * (len(head) - 2)) + " |")
            continue
        params = row["parameters"]
        cells = [label, "x".join(map(str, row["input_size"])),
                 f"{_count(params['total'])} ({_count(params['trainable'], '')})",
                 _count(row["flops"], "", 1e9) + (" *" if row.get("uncounted") else ""), _count(row["macs"], "", 1e9)]
        by_batch = {b["batch"]: b for b in row["batches"]}
        for n in batch_sizes:
            b = by_batch.get(n, {})
            cells += [_ms(b.get("forward_ms")), _fps(b.get("forward_fps")), _ms(b.get("forward_decode_ms")),
                      _fps(b.get("forward_decode_fps")), _memory(b.get("peak_memory_bytes"))]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
