"""Sharded training for big VLMs: Lightning's FSDP with one FSDP unit per transformer block of the loaded model.

A config cannot name every family's layer class (LlamaDecoderLayer, Qwen2VLDecoderLayer, CLIPEncoderLayer,
Qwen2VLVisionBlock, ...), so `LayerWrapFSDPStrategy` finds them when Lightning wraps the model: the classes of the
members of every `nn.ModuleList` whose members all share one class named `*Layer` or `*Block` and hold parameters.
That is the language decoder's layers and the vision tower's blocks of every Hugging Face VLM family here; the
embeddings, projector and LM head stay in the root unit. The same classes are the activation-checkpointing units.

`use_orig_params=True` is the default because fine-tuning here mixes frozen and trainable weights inside one block
(a frozen vision tower, LoRA adapters beside frozen base weights), which FSDP's flat parameters only allow with it.
"""

from __future__ import annotations

import logging
from typing import Iterable, Sequence

from pytorch_lightning.strategies import FSDPStrategy
from torch import nn

log = logging.getLogger(__name__)

LAYER_SUFFIXES = ("Layer", "Block")
SHARDING_STRATEGIES = ("FULL_SHARD", "SHARD_GRAD_OP", "NO_SHARD", "HYBRID_SHARD")
STATE_DICT_TYPES = ("full", "sharded")


def deepspeed_strategy(stage: int = 2, offload_optimizer: bool = False, offload_parameters: bool = False, **kwargs):
    """Lightning's DeepSpeedStrategy (ZeRO `stage`, optional CPU offload), checked and with a clear missing-package
    error; other kwargs go to DeepSpeedStrategy (e.g. logging_batch_size_per_gpu, allgather_bucket_size)."""
    if stage not in (1, 2, 3) or isinstance(stage, bool):
        raise ValueError(f"stage: expected 1, 2 or 3 (ZeRO stage), got {stage!r}")
    for name, value in (("offload_optimizer", offload_optimizer), ("offload_parameters", offload_parameters)):
        if not isinstance(value, bool):
            raise ValueError(f"{name}: expected true or false, got {value!r}")
    if offload_parameters and stage != 3:
        raise ValueError(f"offload_parameters: true needs ZeRO stage 3 (parameters are partitioned only there), "
                         f"got stage {stage}")
    import importlib.util

    if importlib.util.find_spec("deepspeed") is None:
        raise ImportError("trainer=deepspeed needs the deepspeed package: DS_BUILD_OPS=0 pip install deepspeed "
                          "(or use trainer=fsdp, which needs nothing more)")
    from pytorch_lightning.strategies import DeepSpeedStrategy

    return DeepSpeedStrategy(stage=stage, offload_optimizer=offload_optimizer, offload_parameters=offload_parameters,
                             **kwargs)


def gathered_state_dict(trainer) -> dict | None:
    """Run on every rank after fit: under FSDP, the LightningModule's whole state dict gathered on rank 0 (on the CPU;
    an empty dict on the other ranks), for saving; None when the model is not sharded (its own weights are whole)."""
    from torch.distributed.fsdp import FullyShardedDataParallel

    model = getattr(trainer, "model", None)
    if not any(isinstance(module, FullyShardedDataParallel) for module in (model.modules() if model else ())):
        return None
    state = trainer.strategy.lightning_module_state_dict()  # FULL_STATE_DICT, rank0_only, offloaded to the CPU
    trainer.strategy.barrier("gathered_state_dict")
    return state


def unwrap(module: nn.Module) -> nn.Module:
    """The module inside any FSDP / activation-checkpoint wrappers, so a wrapped block is seen as its class."""
    for attr in ("_fsdp_wrapped_module", "_checkpoint_wrapped_module"):
        inner = getattr(module, attr, None)
        if isinstance(inner, nn.Module):
            return unwrap(inner)
    return module


def repeated_block_classes(model: nn.Module) -> set[type[nn.Module]]:
    """Classes of the transformer blocks of `model`: members of a ModuleList all of one `*Layer`/`*Block` class."""
    found: set[type[nn.Module]] = set()
    for module in model.modules():
        if not isinstance(module, nn.ModuleList) or len(module) == 0:
            continue
        members = [unwrap(member) for member in module]
        kinds = {type(member) for member in members}
        if len(kinds) != 1:
            continue
        kind = kinds.pop()
        if kind.__name__.endswith(LAYER_SUFFIXES) and any(True for _ in members[0].parameters()):
            found.add(kind)
    return found


def named_classes(model: nn.Module, names: Iterable[str]) -> set[type[nn.Module]]:
    """The classes of `model`'s submodules named in `names`; a ValueError lists names not in the model."""
    wanted = list(names)
    by_name: dict[str, type[nn.Module]] = {}
    for module in model.modules():
        by_name.setdefault(type(unwrap(module)).__name__, type(unwrap(module)))
    missing = [name for name in wanted if name not in by_name]
    if missing:
        hint = sorted(cls.__name__ for cls in repeated_block_classes(model))
        raise ValueError(f"layer_classes: {missing} are not module classes of this model; "
                         f"its repeated blocks are {hint}")
    return {by_name[name] for name in wanted}


def layer_classes(model: nn.Module, names: Sequence[str] | None = None) -> set[type[nn.Module]]:
    """The FSDP unit classes for `model`: `names` when given, else its repeated blocks (an error when none)."""
    if names:
        return named_classes(model, names)
    found = repeated_block_classes(model)
    if not found:
        raise ValueError(f"model: no repeated transformer blocks found in {type(model).__name__} (a ModuleList of "
                         f"*Layer/*Block modules); name them with trainer.strategy.layer_classes=[ClassName,...]")
    return found


def layer_wrap_policy(model: nn.Module, names: Sequence[str] | None = None):
    """A torch FSDP ModuleWrapPolicy wrapping each block of `model` (see `layer_classes`) as its own unit."""
    from torch.distributed.fsdp.wrap import ModuleWrapPolicy

    return ModuleWrapPolicy(layer_classes(model, names))


def fsdp_units(model: nn.Module) -> dict[str, int]:
    """Class name -> number of FSDP units wrapping a module of that class in `model` (the root unit included)."""
    from torch.distributed.fsdp import FullyShardedDataParallel

    counts: dict[str, int] = {}
    for module in model.modules():
        if isinstance(module, FullyShardedDataParallel):
            name = type(unwrap(module)).__name__
            counts[name] = counts.get(name, 0) + 1
    return counts


def checkpointed_blocks(model: nn.Module) -> dict[str, int]:
    """Class name -> number of modules of that class under an activation-checkpoint wrapper in `model`."""
    from torch.distributed.algorithms._checkpoint.checkpoint_wrapper import CheckpointWrapper

    counts: dict[str, int] = {}
    for module in model.modules():
        if isinstance(module, CheckpointWrapper):
            name = type(unwrap(module)).__name__
            counts[name] = counts.get(name, 0) + 1
    return counts


class LayerWrapFSDPStrategy(FSDPStrategy):
    """Lightning's FSDPStrategy whose auto-wrap (and activation-checkpoint) units are the loaded model's blocks."""

    strategy_name = "fsdp_layers"

    def __init__(self, layer_classes: Sequence[str] | None = None, checkpoint_activations: bool = False,
                 sharding_strategy: str = "FULL_SHARD", state_dict_type: str = "full", use_orig_params: bool = True,
                 cpu_offload: bool = False, **kwargs):
        """FSDP over the model's blocks (or the classes named in `layer_classes`); other kwargs go to FSDP."""
        if isinstance(layer_classes, str) or not (layer_classes is None or all(
                isinstance(name, str) and name for name in layer_classes)):
            raise ValueError(f"layer_classes: expected null or a list of class names, got {layer_classes!r}")
        if sharding_strategy not in SHARDING_STRATEGIES:
            raise ValueError(f"sharding_strategy: expected one of {', '.join(SHARDING_STRATEGIES)}, "
                             f"got {sharding_strategy!r}")
        if state_dict_type not in STATE_DICT_TYPES:
            raise ValueError(f"state_dict_type: expected one of {', '.join(STATE_DICT_TYPES)}, got {state_dict_type!r}")
        for name, value in (("checkpoint_activations", checkpoint_activations), ("use_orig_params", use_orig_params),
                            ("cpu_offload", cpu_offload)):
            if not isinstance(value, bool):
                raise ValueError(f"{name}: expected true or false, got {value!r}")
        super().__init__(sharding_strategy=sharding_strategy, state_dict_type=state_dict_type,
                         use_orig_params=use_orig_params, cpu_offload=cpu_offload, **kwargs)
        self.layer_class_names = list(layer_classes) if layer_classes else None
        self.checkpoint_activations = checkpoint_activations
        self.wrapped_classes: set[type[nn.Module]] = set()

    def _setup_model(self, model: nn.Module) -> nn.Module:
        """Find the block classes of the model about to be wrapped, then wrap (and checkpoint) by them."""
        from torch.distributed.fsdp import FullyShardedDataParallel
        from torch.distributed.fsdp.wrap import ModuleWrapPolicy

        if not any(isinstance(module, FullyShardedDataParallel) for module in model.modules()):
            self.wrapped_classes = layer_classes(model, self.layer_class_names)
            if self.root_device.type == "cpu":  # wrapped here; Lightning's own wrap passes device_id=None, which
                model = self._wrap_on_cpu(model, ModuleWrapPolicy(self.wrapped_classes))  # FSDP refuses on CPU
            else:
                self.kwargs["auto_wrap_policy"] = ModuleWrapPolicy(self.wrapped_classes)
            if self.checkpoint_activations:  # Lightning applies these after wrapping, as FSDP requires
                self._activation_checkpointing_kwargs = {"auto_wrap_policy": ModuleWrapPolicy(self.wrapped_classes)}
            log.info("FSDP units: %s%s", sorted(cls.__name__ for cls in self.wrapped_classes),
                     " (activation checkpointing on)" if self.checkpoint_activations else "")
        return super()._setup_model(model)

    def _wrap_on_cpu(self, model: nn.Module, policy) -> nn.Module:
        """FSDP-wrap `model` on CPU (gloo) as Lightning would, but with device_id=cpu, which torch's FSDP needs
        there."""
        import torch
        from torch.distributed.fsdp import FullyShardedDataParallel

        kwargs = {key: value for key, value in self.kwargs.items() if key != "auto_wrap_policy"}
        return FullyShardedDataParallel(module=model, cpu_offload=self.cpu_offload,
                                        mixed_precision=self.mixed_precision_config,
                                        sharding_strategy=self.sharding_strategy, device_id=torch.device("cpu"),
                                        auto_wrap_policy=policy, **kwargs)
