"""Inference through CUDA graphs: a network's forward captured once per input shape and replayed.

At batch 1 on a fast GPU the heads of many small operations (CLRNet's three refinement stages, LaneATT's
attention over anchors) spend their time launching kernels, not computing: an H200 ran CLRNet-R18's batch 32 in
11.2 ms and its batch 1 in 10.8 ms. A CUDA graph launches the whole recorded forward at once; the kernels, and so
the outputs, are the ones the eager forward runs (benchmarks/bench_families.py --modes eager,graph checks them).

Used where it cannot change what the network computes: a CUDA input, gradients off, the network in eval mode, no
autocast, and no forward hooks anywhere in it (a hook runs while a graph is recorded, never when it is replayed,
so whatever reads activations, like an attention-map plot, needs the eager forward). Anything else, CPU included,
runs the plain forward.
"""

from __future__ import annotations

from typing import Any

import torch
from torch.utils._pytree import tree_map


class GraphedInference:
    """Calls `module(images)`, through a CUDA graph of that forward where that is safe (see the module doc).

    One graph per (shape, dtype, device) of the input, recorded on first use after a few warm-up calls; a replay
    copies the input into the recorded buffer and returns copies of the recorded outputs. The weights are read
    from their storage at every replay, so in-place updates (load_state_dict, an optimiser step) are seen.
    """

    def __init__(self, module: torch.nn.Module, warmup: int = 3):
        self.module = module
        self.warmup = warmup
        self.graphs: dict[tuple, tuple[torch.Tensor, Any, torch.cuda.CUDAGraph]] = {}

    def usable(self, images: torch.Tensor) -> bool:
        return (images.is_cuda and not torch.is_grad_enabled() and not self.module.training
                and not torch.is_autocast_enabled("cuda") and not _has_hooks(self.module))

    def __call__(self, images: torch.Tensor) -> Any:
        if not self.usable(images):
            return self.module(images)
        key = (tuple(images.shape), images.dtype, images.device)
        if key not in self.graphs:
            self.graphs[key] = self._record(images)
        static_input, static_output, graph = self.graphs[key]
        static_input.copy_(images)
        graph.replay()
        return tree_map(lambda t: t.clone() if isinstance(t, torch.Tensor) else t, static_output)

    def _record(self, images: torch.Tensor) -> tuple[torch.Tensor, Any, torch.cuda.CUDAGraph]:
        static_input = images.clone()
        side = torch.cuda.Stream(device=images.device)
        side.wait_stream(torch.cuda.current_stream(images.device))
        with torch.cuda.stream(side):  # warm-up off the default stream, as torch.cuda.graph asks
            for _ in range(self.warmup):
                self.module(static_input)
        torch.cuda.current_stream(images.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            static_output = self.module(static_input)
        return static_input, static_output, graph


def _has_hooks(module: torch.nn.Module) -> bool:
    return any(m._forward_hooks or m._forward_pre_hooks for m in module.modules())

