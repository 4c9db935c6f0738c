"""The visual defenses on a VLM's frames during fine-tuning: the vision layer's tokens laid on the frames (each
tiny family), AAM++ banking and mixing regions of a VLM's frames through the stock callback, PGD on the float frames,
MixUp of whole clips."""

from __future__ import annotations

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader

from lanevil_dev.tiny_vlm import FAMILIES
from lanevil_train.callbacks import AttentionAreaMixing, BatchAdapter, PGDAdversarialTraining
from lanevil_train.data.mixers import MixUp
from lanevil_train.vlm.backends.hf import HFVLM
from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite
from lanevil_train.vlm.clips.qa_data import ClipQADataset, MixingClipCollate, clip_images, collate_clip_qa
from lanevil_train.vlm.training.finetune import VLMFineTuner
from lanevil_train.vlm.training.vision_maps import VISION_LAYERS, VisionMaps

H, W = 32, 48
LORA = {"r": 4, "alpha": 8, "dropout": 0.0}


def _layer_tokens(vlm: HFVLM, clips: torch.Tensor):
    """The family's vision layer output for a [1, 6, 3, H, W] clip, and the maps laid from it."""
    grabbed = {}

    def keep(module, inputs, output):
        grabbed["tokens"] = (output if torch.is_tensor(output) else list(output.values())[-1]).detach()

    handle = vlm.model.get_submodule(VISION_LAYERS[vlm.model_type]).register_forward_hook(keep)
    try:
        batch = vlm.encode(clips, ["How many lanes are there?"], ["Three."])
        with torch.no_grad():
            vlm.loss_from_embeds(batch, vlm.embed(batch))
    finally:
        handle.remove()
    maps = VisionMaps(vlm.processor, vlm.model_type, vlm.frames_as)
    maps.observe(batch.inputs, clips.shape[0], clips.shape[1], (H, W))
    return maps(grabbed["tokens"])


@pytest.mark.parametrize("family", FAMILIES)
def test_the_vision_layers_tokens_land_where_their_part_of_the_frame_is(family, tiny_hf_vlm):
    """A bright block in every frame changes the family's vision tokens most in the map cell over that block
    (LLaVA's processor crops the centre square: its map leaves the cut-off sides empty)."""
    vlm = tiny_hf_vlm(family)
    grey = torch.full((1, 6, 3, H, W), 0.3)
    plain = _layer_tokens(vlm, grey)
    assert plain.shape[:2] == (6, plain.shape[1]) and plain.ndim == 4
    for y0, x0 in ((0, 8), (16, 28)):  # inside LLaVA's centre crop too (its columns 8..40)
        bright = grey.clone()
        bright[..., y0:y0 + 14, x0:x0 + 12] = 1.0
        change = (_layer_tokens(vlm, bright) - plain).norm(dim=1)
        for frame in range(6):
            rows, cols = change.shape[1:]
            i, j = divmod(int(change[frame].argmax()), cols)
            y, x = (i + 0.5) * H / rows, (j + 0.5) * W / cols
            assert y0 - H / rows <= y <= y0 + 14 + H / rows and x0 - W / cols <= x <= x0 + 12 + W / cols, \
                (family, frame, (y, x), (y0, x0))
    if family == "llava":
        assert (plain[0, :, :, 0] == 0).all() and (plain[0, :, :, -1] == 0).all()  # outside the crop
        assert (plain[0, :, :, 1:-1].abs().sum(0) > 0).all()


def _suite_loader(batch_size: int = 2, collate=collate_clip_qa):
    suite = SyntheticClipSuite(1, 700, illusions=["fence_shadow"], severities=(3,), size=(H, W), per_clip=2)
    return DataLoader(ClipQADataset(suite, "all"), batch_size=batch_size, shuffle=False, collate_fn=collate)


def _trainer(tmp_path, steps: int, callback) -> pl.Trainer:
    return pl.Trainer(max_steps=steps, callbacks=[callback], accelerator="cpu", devices=1, logger=False,
                      enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                      default_root_dir=tmp_path, num_sanity_val_steps=0)


def test_aam_plus_plus_banks_regions_of_a_vlms_frames_and_mixes_them_into_later_frames(tiny_vlm_dir, tmp_path):
    """The stock callback on a LoRA-wrapped VLM with a frozen vision tower: its layer is the family's vision output
    under peft's names, the frames take gradients so the frozen layer gets them, the hard frames' regions are banked
    and later frames receive them (the images the step saw differ from the clips' own)."""
    module = VLMFineTuner(str(tiny_vlm_dir("qwen2_vl")), lora=LORA)
    layer = module.attention_layer("auto")
    assert layer == "model.base_model.model.model.visual"
    aam = AttentionAreaMixing(layer=layer, mode="aam++", feature_map=module.vision_maps, min_area=0.001,
                              mix_prob=1.0, adapter=BatchAdapter(images="images", lanes="lanes"), seed=1)
    seen = []

    class Spy(pl.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            seen.append((batch["images"].clone(), batch["keys"]))

    trainer = pl.Trainer(max_steps=4, callbacks=[aam, Spy()], accelerator="cpu", devices=1, logger=False,
                         enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                         default_root_dir=tmp_path, num_sanity_val_steps=0)
    loader = _suite_loader()
    trainer.fit(module, loader)
    assert module.attention_gradients is True
    assert aam.stats["hard"] > 0 and aam.stats["banked"] > 0 and len(aam.bank) > 0
    assert aam.stats["mixed"] > 0
    clean = {tuple(keys): clip_images(batch["frames"]) for batch in loader for keys in [batch["keys"]]}
    changed = [not torch.equal(images, clean[tuple(keys)]) for images, keys in seen[1:]]
    assert any(changed)  # a later batch's frames carry banked regions
    for patch in [p for queue in aam.bank.regions.values() for p in queue]:
        assert patch.shape[0] == 3 and patch.shape[1] <= H and patch.shape[2] <= W


def test_pgd_on_a_vlms_frames_stays_in_its_ball_and_raises_the_loss(tiny_vlm_dir):
    """PGD in [0, 1] pixel units on the float frames: every pixel within eps of the clean one and inside [0, 1],
    and the answers' loss higher on the adversarial frames."""
    module = VLMFineTuner(str(tiny_vlm_dir("qwen2_vl")), lora=LORA)
    module.model.eval()
    batch = module.on_after_batch_transfer(next(iter(_suite_loader())), 0)
    pgd = PGDAdversarialTraining(eps=8 / 255, step_size=2 / 255, steps=4, mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0),
                                 adapter=BatchAdapter(images="images"), seed=0)
    clean = batch["images"].clone()
    adversarial = pgd.attack(module, batch, batch["images"])
    assert torch.equal(batch["images"], clean)  # the batch is left as it was
    assert float((adversarial - clean).abs().max()) <= 8 / 255 + 1e-6
    assert float(adversarial.min()) >= 0.0 and float(adversarial.max()) <= 1.0
    with torch.no_grad():
        before = module.batch_loss(batch).mean().item()
        after = module.batch_loss({**batch, "images": adversarial}).mean().item()
    assert after > before + 1e-4


def test_mixup_blends_whole_clips_and_keeps_each_clips_questions():
    """MixUp on a VLM batch: a mixed clip's 6 frames are one blend of its own and one partner clip's frames (one
    weight for all six), its question, answer and lanes its own."""
    items = [ClipQADataset(SyntheticClipSuite(1, 700 + k, illusions=["road_crack"], severities=(2,), size=(H, W),
                                              per_clip=1), "clean")[0] for k in range(3)]
    mixer = MixUp(alpha=1.0, p=1.0, seed=3)
    batch = MixingClipCollate(mixer)(items)
    plain = collate_clip_qa(items)
    assert batch["questions"] == plain["questions"] and batch["answers"] == plain["answers"]
    assert len(batch["lanes"]) == 18 and all(np.array_equal(a, b) for f, g in zip(batch["lanes"], plain["lanes"])
                                             for a, b in zip(f, g))
    partners, lams = mixer.plan(3, np.random.default_rng([3, 0]))
    for i, (j, lam) in enumerate(zip(partners, lams)):
        expected = (lam * items[i]["frames"].astype(np.float64)
                    + (1 - lam) * items[j]["frames"].astype(np.float64)).astype(np.uint8)
        assert np.array_equal(batch["frames"][i].numpy(), expected)
        assert not np.array_equal(batch["frames"][i].numpy(), items[i]["frames"])
