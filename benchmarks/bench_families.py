"""Every detector family at its paper's input size: parameters, forward latency and peak memory (CPU), and
batch-1 / batch-32 throughput on a GPU when one is there, next to the published FPS of the original code.

Usage: python benchmarks/bench_families.py [--families laneatt,ufld,...] [--device cpu|cuda]
                                           [--batches 1,32] [--repeats 10] [--threads 2] [--json out.jsonl]
                                           [--modes eager,graph,compile] [--timeout 300]

Each family is built by build_model from its conf/model config, with ResNet-18 (SCNN: VGG-16, as its paper), in
a process of its own so that peak memory (ru_maxrss on CPU, max_memory_allocated on a GPU) is its own. Timed is
LaneDetector.forward (the network: what the ONNX export holds); "decode" adds the family's Python decoding
(NMS, lane assembly) of a batch-1 output, on the host. On a GPU, --modes adds the forward through CUDA graphs
(what evaluation runs there) and torch.compile, each with its largest output difference from the eager forward.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import torch

# (input size of the paper's CULane / TuSimple setting, backbone, published FPS and where it was measured)
FAMILIES = {
    "laneatt": ((360, 640), "resnet18", "250 (LaneATT paper, RTX 2080 Ti)"),
    "ufld": ((288, 800), "resnet18", "306 (UFLD paper, GTX 1080 Ti)"),
    "clrnet": ((320, 800), "resnet18", "206 (CLRNet paper, NVIDIA 1080 Ti)"),
    "scnn": ((288, 800), "vgg16", "7.5 (SCNN in the UFLD paper's comparison, GTX 1080 Ti)"),
    "bezierlanenet": ((288, 800), "resnet18", "213 (BezierLaneNet paper, ResNet-18)"),
    "ganet": ((320, 800), "resnet18", "153 (GANet paper, GANet-S / ResNet-18)"),
    "laneformer": ((320, 800), "resnet18", "none published for ResNet-18 (no official code)"),
    "clrernet": ((320, 800), "resnet18", "none published (CLRerNet README: DLA-34 only, 18.4 GFLOPs)"),
}


def build(family: str):
    from hydra import compose, initialize_config_module

    from lanevil_train.tasks.builders import build_model, model_config

    size, backbone, _ = FAMILIES[family]
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"model={family}", f"backbone={backbone}",
                                                       f"data.input_size=[{size[0]},{size[1]}]", "data.max_lanes=4"])
    torch.manual_seed(0)
    return build_model(model_config(cfg)).eval()


def _time(fn, repeats: int, sync) -> float:
    """The median seconds of `repeats` calls after 3 untimed ones (task=profile's timing)."""
    from lanevil_train.models.profile import time_call

    return time_call(fn, 3, repeats, sync)["median_ms"] / 1e3


def _max_difference(a, b) -> float:
    """The largest absolute difference between two outputs (dicts/tuples of tensors) of one network."""
    from torch.utils._pytree import tree_leaves

    pairs = zip(tree_leaves(a), tree_leaves(b))
    return max((float((x.float() - y.float()).abs().max()) for x, y in pairs if isinstance(x, torch.Tensor)),
               default=0.0)


def _forward(model, mode: str):
    """The inference forward of `mode`: eager, graph (models/cuda_graphs.py, what evaluation uses on a GPU) or
    compile (torch.compile, default mode)."""
    from lanevil_train.models.cuda_graphs import GraphedInference

    if mode == "graph":
        return GraphedInference(model)
    if mode == "compile":
        return torch.compile(model)
    return model


def measure(family: str, device: str, batches: list[int], repeats: int, modes: list[str]) -> dict:
    size, backbone, published = FAMILIES[family]
    model = build(family).to(device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    row = {"family": family, "backbone": backbone, "input": f"{size[0]}x{size[1]}", "device": device,
           "params_M": round(sum(p.numel() for p in model.parameters()) / 1e6, 2), "published_fps": published}
    if device == "cuda":
        row["gpu"] = torch.cuda.get_device_name()
        torch.backends.cudnn.benchmark = True
    with torch.inference_mode():
        for mode in modes:
            forward = _forward(model, mode)
            prefix = "" if mode == "eager" else f"{mode}_"
            for batch in batches:
                images = torch.randn(batch, 3, *size, device=device, generator=torch.Generator(device).manual_seed(0))
                started = time.perf_counter()
                out = forward(images)  # a graph is recorded, a compiled model compiled, on the first call
                sync()
                if mode != "eager":
                    row[f"{prefix}b{batch}_first_call_s"] = round(time.perf_counter() - started, 1)
                    row[f"{prefix}b{batch}_max_diff"] = _max_difference(out, model(images))
                seconds = _time(lambda: forward(images), repeats, sync)
                row[f"{prefix}b{batch}_ms"] = round(seconds * 1e3, 2)
                row[f"{prefix}b{batch}_fps"] = round(batch / seconds, 1)
            images = torch.randn(1, 3, *size, device=device)
            row[f"{prefix}b1_decode_ms"] = round(_time(lambda: model.decode_lanes(forward(images), size, [size]),
                                                       repeats, sync) * 1e3, 2)
    if device == "cuda":
        row["peak_gpu_MB"] = round(torch.cuda.max_memory_allocated() / 2**20)
    row["peak_rss_MB"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--batches", default=None, help="default: 1 on cpu, 1,32 on cuda")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--modes", default="eager", help="comma-separated: eager, graph (CUDA graphs, as evaluation "
                        "runs on a GPU), compile (torch.compile); each non-eager mode's largest output difference "
                        "from eager is reported")
    parser.add_argument("--timeout", type=float, default=None, help="seconds one family may take")
    parser.add_argument("--json", default=None, help="append each family's row to this JSON-lines file")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)  # the per-family child process
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    batches = [int(b) for b in (args.batches or ("1,32" if args.device == "cuda" else "1")).split(",")]
    if args.one:
        print(json.dumps(measure(args.one, args.device, batches, args.repeats, args.modes.split(","))))
        return
    rows = []
    for family in args.families.split(","):
        cmd = [sys.executable, __file__, "--one", family, "--device", args.device, "--batches",
               ",".join(map(str, batches)), "--repeats", str(args.repeats), "--threads", str(args.threads),
               "--modes", args.modes]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
        except subprocess.TimeoutExpired:
            print(f"{family}: over {args.timeout} s", file=sys.stderr)
            continue
        if proc.returncode != 0:
            print(f"{family}: failed\n{proc.stderr[-3000:]}", file=sys.stderr)
            continue
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
        if args.json:
            with open(args.json, "a", encoding="utf-8") as handle:
                handle.write(json.dumps(rows[-1]) + "\n")
    timed = [k for k in rows[0] if k.endswith(("_ms", "_fps", "_diff")) and k != "published_fps"] if rows else []
    keys = ["family", "backbone", "input", "params_M", *timed,
            *(["peak_gpu_MB"] if args.device == "cuda" else []), "peak_rss_MB", "published_fps"] if rows else []
    print("\n| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join(str(row.get(k, "")) for k in keys) + " |")


if __name__ == "__main__":
    main()
