"""Fine-tuning Hugging Face VLMs through Lightning, on the tiny random-weight models (CPU, 32x48 frames)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset, Subset

from lanevil_train.callbacks.adapter import BatchAdapter
from lanevil_train.vlm.backends.hf import HFVLM, IGNORE_INDEX
from lanevil_train.vlm.training.finetune import (
    ClipQADataset,
    VLMFineTuner,
    clip_images,
    collate_clip_qa,
    vision_tower_names,
)

QA = [("How many lanes does the road have?", "The road has three lanes."), ("Is it wet?", "Yes."),
      ("What should the ego vehicle do next?", "Keep the lane."), ("Is there a crack ahead?", "No.")]
LORA = {"r": 4, "alpha": 8, "dropout": 0.0}


class FixedQA(Dataset):
    """Four (clip, question, answer) items of random 32x48 frames, fixed by seed."""

    def __init__(self, seed: int = 3):
        rng = np.random.default_rng(seed)
        self.frames = [rng.integers(0, 256, (6, 32, 48, 3), dtype=np.uint8) for _ in QA]

    def __len__(self) -> int:
        return len(QA)

    def __getitem__(self, i: int) -> dict:
        return {"frames": self.frames[i], "question": QA[i][0], "answer": QA[i][1], "key": f"c{i}/q{i}",
                "meta": {"clip_id": f"c{i}"}}


@pytest.fixture(scope="module")
def batch():
    return collate_clip_qa([FixedQA()[i] for i in range(2)])


def _steps(module: VLMFineTuner, batch: dict, steps: int, lr: float = 1e-2) -> list[float]:
    """Plain AdamW steps on one batch; the losses before each step."""
    optimizer = torch.optim.AdamW([p for p in module.parameters() if p.requires_grad], lr=lr)
    module.train()
    losses = []
    for _ in range(steps):
        loss = module.batch_loss(batch).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    return losses


def _trainer(tmp_path, max_steps: int, callbacks=()) -> pl.Trainer:
    from pytorch_lightning.callbacks import ModelCheckpoint

    checkpointing = any(isinstance(callback, ModelCheckpoint) for callback in callbacks)
    return pl.Trainer(max_steps=max_steps, callbacks=list(callbacks), accelerator="cpu", devices=1, logger=False,
                      enable_checkpointing=checkpointing,
                      enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path,
                      num_sanity_val_steps=0, deterministic=True)


def test_batches_carry_uint8_frames_that_become_the_float_images_defenses_edit_and_the_loss_reads(batch,
                                                                                                   tiny_vlm_dir):
    """The collated frames are one uint8 [B, 6, H, W, 3] tensor; after the transfer to the device the step's batch
    holds them as float (B*6, 3, H, W) images in [0, 1], which a BatchAdapter addresses: an edit to them is what
    the model sees (the loss changes), and the uint8 batch gives the loss of its frames."""
    assert batch["frames"].dtype == torch.uint8 and tuple(batch["frames"].shape) == (2, 6, 32, 48, 3)
    assert batch["questions"] == [QA[0][0], QA[1][0]] and batch["answers"] == [QA[0][1], QA[1][1]]
    module = VLMFineTuner(str(tiny_vlm_dir("qwen2_vl")), lora=LORA)
    moved = module.on_after_batch_transfer({**batch}, 0)
    assert "frames" not in moved
    images = BatchAdapter(images="images").images(moved)
    assert images.dtype == torch.float32 and tuple(images.shape) == (12, 3, 32, 48)
    assert torch.equal(images[7, :, 5, 9] * 255, batch["frames"][1, 1, 5, 9].float())
    assert torch.equal(clip_images(batch["frames"]), images)
    with torch.no_grad():
        from_frames = module.batch_loss(batch)
        from_images = module.batch_loss(moved)
        assert torch.allclose(from_frames, from_images)
        images[6:12] = 1.0 - images[6:12]  # the second clip's frames edited in place
        edited = module.batch_loss(moved)
    assert edited[0] == pytest.approx(float(from_images[0]), rel=1e-6)
    assert abs(float(edited[1] - from_images[1])) > 1e-4


def test_the_loss_reaches_the_pixels_through_the_processor(tiny_vlm_dir, batch):
    """Training's float images go through the processor's own torch operations: the loss has a gradient at every
    frame, equal to a finite difference, and the uint8 path (evaluation's) gives the same loss."""
    module = VLMFineTuner(str(tiny_vlm_dir("qwen2_vl")), lora=LORA)
    module.model.double()
    hf = module.vlm()
    images = clip_images(batch["frames"]).double().requires_grad_(True)
    clips = images.unflatten(0, (2, 6))

    def loss(pixels):
        encoded = hf.encode(pixels, batch["questions"], batch["answers"])
        return hf.loss_from_embeds(encoded, hf.embed(encoded)).sum()

    value = loss(clips)
    (grad,) = torch.autograd.grad(value, images)
    assert (grad.flatten(1).abs().sum(1) > 0).all()  # every frame of both clips
    with torch.no_grad():
        frames = [list(clip) for clip in batch["frames"].numpy()]
        uint8 = hf.encode(frames, batch["questions"], batch["answers"])
        assert float(hf.loss_from_embeds(uint8, hf.embed(uint8)).sum()) == pytest.approx(float(value), rel=2e-3)
        direction = torch.zeros_like(images)
        direction[3, 1, 10:20, 20:30] = 1.0
        direction *= (images > 0.01) & (images < 0.99)  # the step stays inside [0, 1]
        eps = 1e-3
        estimate = (loss((images + eps * direction).unflatten(0, (2, 6)))
                    - loss((images - eps * direction).unflatten(0, (2, 6)))) / (2 * eps)
    assert float((grad * direction).sum()) == pytest.approx(float(estimate), rel=1e-4)


def test_clip_qa_dataset_pairs_each_chosen_clip_with_its_qa():
    """clean: only severity-0 clips, each with every QA of its base clip; all: the perturbed variants too."""
    from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite

    suite = SyntheticClipSuite(1, 500, illusions=["road_crack"], severities=(3,), size=(32, 48), per_clip=2)
    clean, every = ClipQADataset(suite, "clean"), ClipQADataset(suite, "all")
    clean_clips = [i for i in range(len(suite)) if suite.clip_meta(i)["severity"] == 0]
    expected = sum(len(suite.qa_for(suite.clip_meta(i)["base_clip_id"])) for i in clean_clips)
    assert len(clean) == expected and len(every) == 2 * expected
    item = clean[0]
    qa = suite.qa_for(item["meta"]["base_clip_id"])[0]
    assert item["frames"].dtype == np.uint8 and item["frames"].shape == (6, 32, 48, 3)
    assert (item["question"], item["answer"]) == (qa["question"], qa["answer"])
    assert item["meta"]["severity"] == 0 and item["meta"]["qa_type"] == qa["type"]
    assert {every[i]["meta"]["severity"] for i in range(len(every))} == {0, 3}
    assert len(ClipQADataset(suite, "all", limit=3)) == 3
    with pytest.raises(ValueError, match="variants"):
        ClipQADataset(suite, "perturbed")


@pytest.mark.parametrize("family", ["llava", "qwen2_vl"])
def test_labels_are_the_answer_and_its_end_token_only(family, tiny_vlm_dir, batch):
    """Every prompt, frame and question position is IGNORE_INDEX; the labelled tokens are the answer, then the
    end-of-turn token when train_eos (the tiny LLaVA template ends no turn, so </s> is inserted)."""
    module = VLMFineTuner(str(tiny_vlm_dir(family)), lora=LORA)
    hf = module.vlm()
    clips = [list(clip) for clip in batch["frames"].numpy()]
    plain = hf.encode(clips, batch["questions"], batch["answers"])
    with_eos = hf.encode(clips, batch["questions"], batch["answers"], label_eos=True)
    tokenizer, eos = hf.processor.tokenizer, {"llava": "</s>", "qwen2_vl": "<|im_end|>"}[family]
    for i in range(2):
        start, end = plain.answer_spans[i]
        assert (plain.labels[i, :start] == IGNORE_INDEX).all() and (plain.labels[i, end:] == IGNORE_INDEX).all()
        labelled = with_eos.labels[i][with_eos.labels[i] != IGNORE_INDEX]
        assert tokenizer.decode(labelled).strip() == batch["answers"][i] + eos
        q_start, q_end = with_eos.question_spans[i]
        assert (with_eos.labels[i, :q_end] == IGNORE_INDEX).all()
        assert tokenizer.decode(with_eos.inputs["input_ids"][i, q_start:q_end]).strip() == batch["questions"][i]
    # the loss is the NLL of exactly the labelled tokens: recomputed from the logits with the labels of the answer
    # (+ end token) positions only, and changing the labels at any other position would change nothing
    module.hparams.train_eos = True
    loss = module.batch_loss(batch).detach()
    with torch.no_grad():
        logits = hf.model(**with_eos.inputs).logits.float()
    log_probs = torch.log_softmax(logits[:, :-1], dim=-1)
    targets = with_eos.inputs["input_ids"][:, 1:]
    mask = with_eos.labels[:, 1:] != IGNORE_INDEX
    nll = -log_probs.gather(-1, targets.unsqueeze(-1)).squeeze(-1)
    manual = (nll * mask).sum(1) / mask.sum(1)
    assert torch.allclose(loss, manual, rtol=1e-4)
    assert ((with_eos.labels != IGNORE_INDEX).sum(1) == (plain.labels != IGNORE_INDEX).sum(1) + 1).all()


@pytest.mark.parametrize("family", ["llava", "qwen2_vl"])
def test_lora_steps_reduce_the_loss_train_only_adapters_and_the_saved_adapter_reloads(family, tiny_vlm_dir, batch,
                                                                                        tmp_path):
    """A few LoRA steps lower the answer loss; every base weight stays bit-identical; the saved adapter, loaded
    on the base model (merged or not), gives the trained module's logits and answers."""
    base_dir = tiny_vlm_dir(family)
    torch.manual_seed(0)
    module = VLMFineTuner(str(base_dir), lora=LORA)
    trainable = {n for n, p in module.named_parameters() if p.requires_grad}
    assert trainable and all("lora_" in n for n in trainable)
    assert not any(any(v + "." in n for v in ("vision_tower", "visual")) for n in trainable)
    before = {n: p.detach().clone() for n, p in module.named_parameters() if not p.requires_grad}
    losses = _steps(module, batch, 8)
    assert losses[-1] < losses[0] - 0.2, losses
    assert all(torch.equal(before[n], p) for n, p in module.named_parameters() if n in before)
    trained = module.vlm(max_new_tokens=4)
    clips = [list(clip) for clip in batch["frames"].numpy()]
    reference_loss = trained.answer_loss(clips, batch["questions"], batch["answers"]).detach()
    reference_answers = trained.answer(clips, batch["questions"])

    adapter = module.save_model(tmp_path / "adapter")
    assert json.loads((adapter / "adapter_config.json").read_text())["peft_type"] == "LORA"
    merged_dir = module.save_model(tmp_path / "merged", merge=True)
    assert not (merged_dir / "adapter_config.json").exists()
    for loaded in (HFVLM(base_dir, device="cpu", dtype="float32", max_new_tokens=4, adapter=adapter),
                   HFVLM(base_dir, device="cpu", dtype="float32", max_new_tokens=4, adapter=adapter,
                         merge_adapter=True),
                   HFVLM(merged_dir, device="cpu", dtype="float32", max_new_tokens=4)):
        got = loaded.answer_loss(clips, batch["questions"], batch["answers"]).detach()
        assert torch.allclose(got, reference_loss, atol=1e-5), (got, reference_loss)
        assert loaded.answer(clips, batch["questions"]) == reference_answers
    fresh = HFVLM(base_dir, device="cpu", dtype="float32")
    assert not torch.allclose(fresh.answer_loss(clips, batch["questions"], batch["answers"]).detach(),
                              reference_loss, atol=1e-3)


def test_an_adapter_that_is_not_one_or_does_not_fit_is_refused_naming_the_path(tiny_vlm_dir, tmp_path):
    """A model directory given as an adapter, and a LLaVA adapter on a Qwen2-VL model, are errors naming the path."""
    with pytest.raises(ValueError, match="no adapter_config.json"):
        HFVLM(tiny_vlm_dir("qwen2_vl"), device="cpu", adapter=tiny_vlm_dir("llava"))
    module = VLMFineTuner(str(tiny_vlm_dir("llava")), lora={**LORA, "target_modules": ["q_proj"]})
    adapter = module.save_model(tmp_path / "llava_adapter")
    config = json.loads((adapter / "adapter_config.json").read_text())
    config["r"] = 8  # the saved weights are rank 4: they no longer fit the model peft builds
    (adapter / "adapter_config.json").write_text(json.dumps(config))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match=str(adapter)):
            HFVLM(tiny_vlm_dir("llava"), device="cpu", adapter=adapter)


def test_full_fine_tuning_with_a_frozen_vision_tower_changes_only_the_rest(tiny_vlm_dir, batch, tmp_path):
    """Full fine-tuning trains the language model but leaves the vision tower bit-identical; the saved model
    reloads as a plain model directory with the trained loss."""
    torch.manual_seed(0)
    module = VLMFineTuner(str(tiny_vlm_dir("llava")), lora=None, freeze_vision=True)
    assert vision_tower_names(module.model) == ["model.vision_tower"]
    vision = {n: p.detach().clone() for n, p in module.model.model.vision_tower.named_parameters()}
    language = module.model.model.language_model.layers[0].self_attn.q_proj.weight.detach().clone()
    losses = _steps(module, batch, 5)
    assert losses[-1] < losses[0]
    assert all(torch.equal(vision[n], p) for n, p in module.model.model.vision_tower.named_parameters())
    assert not torch.equal(language, module.model.model.language_model.layers[0].self_attn.q_proj.weight)
    clips = [list(clip) for clip in batch["frames"].numpy()]
    expected = module.vlm().answer_loss(clips, batch["questions"], batch["answers"]).detach()
    saved = HFVLM(module.save_model(tmp_path / "full"), device="cpu", dtype="float32")
    assert torch.allclose(saved.answer_loss(clips, batch["questions"], batch["answers"]).detach(), expected,
                          atol=1e-5)


class StopAt(pl.Callback):
    """Ends a fit after `step` optimizer steps, as a kill would, so the run's schedule is that of the full run."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_end(self, trainer, *args) -> None:
        trainer.should_stop = trainer.should_stop or trainer.global_step >= self.step


def test_resume_continues_at_the_saved_step_and_matches_an_uninterrupted_run(tiny_vlm_dir, tmp_path):
    """A 4-step fit stopped after 2 steps and checkpointed, then fit again from the checkpoint: the global step
    continues to 4 and the weights and the loss equal an uninterrupted 4-step run (adapter weights, AdamW moments
    and the warmup/cosine schedule all restored); the LoRA checkpoint holds only the adapter weights and the base
    model's directory. One batch per epoch: Lightning replays the batch order of a resumed epoch from its start
    (a data-loop matter, not the module's), so the data seen is the same either way."""
    base_dir = str(tiny_vlm_dir("qwen2_vl"))
    loader = DataLoader(Subset(FixedQA(), [0, 1]), batch_size=2, shuffle=False, collate_fn=collate_clip_qa)

    def module() -> VLMFineTuner:
        torch.manual_seed(0)
        return VLMFineTuner(base_dir, lora=LORA, lr=5e-3, warmup_steps=1)

    straight = module()
    _trainer(tmp_path / "a", 4).fit(straight, loader)
    first = module()
    trainer = _trainer(tmp_path / "b", 4, callbacks=[StopAt(2)])
    trainer.fit(first, loader)
    assert trainer.global_step == 2
    checkpoint = tmp_path / "b" / "step2.ckpt"
    trainer.save_checkpoint(checkpoint)
    saved = torch.load(checkpoint, map_location="cpu", weights_only=True)
    assert saved["state_dict"] and all("lora_" in key for key in saved["state_dict"])
    assert saved["hyper_parameters"]["model_dir"] == base_dir and saved["hyper_parameters"]["lora"]["r"] == 4
    resumed = module()
    resumed_trainer = _trainer(tmp_path / "c", 4)
    resumed_trainer.fit(resumed, loader, ckpt_path=checkpoint)
    assert resumed_trainer.global_step == 4
    moved = False
    for (name, a), (_, b), (_, c) in zip(straight.named_parameters(), resumed.named_parameters(),
                                         first.named_parameters()):
        assert torch.allclose(a, b, atol=1e-6), name
        moved = moved or not torch.allclose(b, c, atol=1e-6)
    assert moved, "steps 3 and 4 changed nothing"
    batch = collate_clip_qa([FixedQA()[i] for i in range(2)])
    assert torch.allclose(straight.batch_loss(batch), resumed.batch_loss(batch), atol=1e-5)
    reloaded = VLMFineTuner.load_from_checkpoint(checkpoint)
    assert all(torch.equal(p, dict(first.named_parameters())[n]) for n, p in reloaded.named_parameters())


def test_bad_settings_are_refused_naming_the_argument(tiny_vlm_dir, tmp_path):
    base_dir = str(tiny_vlm_dir("llava"))
    with pytest.raises(ValueError, match="lora.r"):
        VLMFineTuner(base_dir, lora={"r": 0})
    with pytest.raises(ValueError, match="lora: unknown keys rank"):
        VLMFineTuner(base_dir, lora={"rank": 4})
    with pytest.raises(ValueError, match="lora.target_modules: no Linear layer named nope"):
        VLMFineTuner(base_dir, lora={"target_modules": ["nope"]})
    with pytest.raises(ValueError, match="dtype"):
        VLMFineTuner(base_dir, dtype="float64")
    with pytest.raises(FileNotFoundError, match="model.path"):
        VLMFineTuner(str(tmp_path / "missing"))
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "notes.txt").write_text("keep")
    with pytest.raises(FileExistsError, match="precious"):
        VLMFineTuner(base_dir, lora=LORA).save_model(tmp_path / "precious")


class _Numbered(Dataset):
    """24 items in 6 "base clips" of 4: what WindowShuffleSampler reads of a ClipQADataset."""

    def __len__(self) -> int:
        return 24

    def __getitem__(self, i: int) -> int:
        return i

    def base_clip_groups(self) -> list[list[int]]:
        return [list(range(k, k + 4)) for k in range(0, 24, 4)]


class _KeyRecorder(pl.LightningModule):
    """One weight; records which items each optimizer step trained on."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(1))
        self.seen: dict[int, list[int]] = {}

    def training_step(self, batch, batch_idx):
        self.seen[self.global_step] = batch.tolist()
        return (self.weight - batch.float().mean()).pow(2).sum()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


@pytest.mark.parametrize("skip", [True, False], ids=["skip", "replay"])
def test_a_run_resumed_inside_an_epoch_trains_on_the_batches_an_uninterrupted_run_would(tmp_path, skip):
    """12 batches an epoch, 16 steps; stopped and checkpointed at step 5, then resumed: with SkipTrainedBatches the
    resumed steps 5-15 see exactly the uninterrupted run's batches (the rest of epoch 0, then epoch 1's new
    order); without it Lightning restarts epoch 0's data at its first batch."""
    from pytorch_lightning.callbacks import ModelCheckpoint

    from lanevil_train.vlm.clips.qa_data import WindowShuffleSampler
    from lanevil_train.vlm.training.finetune import SkipTrainedBatches

    def fit(root, max_steps, callbacks=(), ckpt_path=None):
        sampler = WindowShuffleSampler(_Numbered(), window=2, seed=5)
        loader = DataLoader(_Numbered(), batch_size=2, sampler=sampler)
        module = _KeyRecorder()
        extra = [SkipTrainedBatches(sampler, 2)] if skip else []
        trainer = _trainer(root, max_steps, callbacks=[*extra, *callbacks])
        trainer.fit(module, loader, ckpt_path=ckpt_path)
        return module.seen, trainer

    straight, _ = fit(tmp_path / "a", 16)
    assert sorted(x for step in range(12) for x in straight[step]) == list(range(24))
    every5 = ModelCheckpoint(dirpath=tmp_path / "b", every_n_train_steps=5, save_top_k=-1)
    fit(tmp_path / "b", 16, callbacks=[every5, StopAt(7)])  # killed at step 7; the last checkpoint is step 5's
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Lightning's "your dataloader is not resumable"
        resumed, trainer = fit(tmp_path / "c", 16, ckpt_path=tmp_path / "b" / "epoch=0-step=5.ckpt")
    assert trainer.global_step == 16 and sorted(resumed) == list(range(5, 16))
    if skip:
        assert resumed == {step: straight[step] for step in range(5, 16)}
    else:
        assert resumed[5] == straight[0]  # the replay the callback prevents
