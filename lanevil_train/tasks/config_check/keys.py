"""The config keys the check treats specially: read by Hydra or by code, supplied by the builders, the textual
defenses' keys, the splits."""

from __future__ import annotations

# Keys of a `_target_` node that Hydra reads itself (not passed to the target).
HYDRA_KEYS = {"_target_", "_recursive_", "_convert_", "_partial_", "_args_"}
# Arguments the code passes to a target itself: a config value for them would be ignored.
SUPPLIED = {"model.head": ("in_channels", "in_strides", "image_size"), "model.neck": ("in_channels", "in_strides")}
# Keys of a VLM model node read by the training code, not arguments of its inference `_target_`; READ_BY_CODE:
# such keys of any target node (the model's kind too).
TRAINING_KEYS = ("lora", "fine_tune", "embedded", "attention_layer")
READ_BY_CODE = {"model": (*TRAINING_KEYS, "kind")}
DEFENSE_KEYS = ("name", "transforms", "mixer", "callback")
# The keys of a textual defense of VLMs (defense=pat++: tasks/vlm/defense.py), beside DEFENSE_KEYS.
PROMPT_DEFENSE_KEYS = ("prompt", "alpha", "hard_target", "hardness", "pool_clips", "examples", "steps",
                       "prefix_length", "suffix_length", "top_k", "num_candidates", "chunk", "soft", "soft_lr",
                       "prefix_path", "before", "after")
SPLITS = ("train", "val", "test")
