"""task=train for VLMs from the command line: LoRA on a saved tiny Hugging Face model and the embedded VLM built
here, a few steps each on tiny clips, the model saved in the run, tested after fit, and evaluated again from the
saved folder and from the checkpoint."""

from __future__ import annotations

import json

import pytest

from lanevil_dev.tiny_vlm import build_tiny_vlm
from lanevil_train.results_log import ResultsLog
from tests.tasks.cli_helpers import run_cli, run_in_process

# model=vlm/<backend> selects data=clips itself: the commands below are the natural forms, with tiny sizes
TINY_CLIPS = ["data.size=[32,48]", "data.train.num_cases=2", "data.val.num_cases=1",
              "data.batch_size=2", "data.illusions=[road_repair]", "data.severities=[3]", "trainer=cpu",
              "trainer.max_steps=3", "trainer.max_epochs=-1", "trainer.log_every_n_steps=1", "judge=none",
              "task.cases=1", "task.illusions=[road_repair]", "task.severities=[3]", "progress=plain"]
TINY_PRETRAINING = ["model.embedded.vision_pretraining.steps=2", "model.embedded.vision_pretraining.clips=2",
                    "model.embedded.vision_pretraining.batch=2"]
ANSWERS = 3 * 2 * 5  # a test case: 3 segments x (clean + 1 severity) x 5 QA


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    return build_tiny_vlm("qwen2_vl", tmp_path_factory.mktemp("models") / "tiny-qwen2-vl")


def test_lora_fine_tuning_saves_an_adapter_tests_it_and_evaluates_it_again(tiny_model, tmp_path):
    run = tmp_path / "train"
    run_cli(["task=train", "model=vlm/hf", f"model.path={tiny_model}", "model.max_new_tokens=4", "model.lora.r=4",
             "+trainer.val_check_interval=3", "trainer.limit_val_batches=2", "data=clips", *TINY_CLIPS], run)
    adapter = run / "model"
    assert (adapter / "adapter_config.json").is_file() and (run / "checkpoints" / "last.ckpt").is_file()
    metrics = (run / "csv" / "metrics.csv").read_text()
    assert "train/loss" in metrics and "val/loss" in metrics
    tested = ResultsLog(run / "test" / "per_answer.jsonl").records()
    assert len(tested) == ANSWERS and json.loads((run / "test" / "main.json").read_text())
    # the same model from its adapter folder and from the checkpoint answers the same questions the same way
    for name, source in (("adapter", [f"model.adapter={adapter}"]),
                         ("ckpt", [f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}"])):
        out = tmp_path / name
        run_in_process(["task=evaluate", "model=vlm/hf", f"model.path={tiny_model}", "model.max_new_tokens=4",
                        "task.suite=synthetic", f"task.out_dir={out}", *source, *TINY_CLIPS], tmp_path / f"eval-{name}")
        answers = {r["key"]: r["answer"] for r in ResultsLog(out / "per_answer.jsonl").records()}
        assert answers == {r["key"]: r["answer"] for r in tested}


def test_the_embedded_vlm_is_built_from_the_training_qa_trained_and_saved(tmp_path):
    run = tmp_path / "train"
    run_in_process(["task=train", "model=vlm/embedded", "model.embedded.frame_size=[32,48]", "model.max_new_tokens=4",
                    *TINY_PRETRAINING, *TINY_CLIPS], run)  # the quickstart's test below goes through the command line
    assert (run / "init" / "config.json").is_file() and (run / "model" / "config.json").is_file()
    assert len(ResultsLog(run / "test" / "per_answer.jsonl").records()) == ANSWERS


def test_the_vlm_quickstart_trains_the_embedded_vlm_and_tables_it_beside_its_blind_baseline(tmp_path):
    """experiment=vlm_quickstart, shrunk (tiny frames, 3 steps, one test case): the embedded VLM built, trained
    with validation, saved, and tested on the clips and on grey frames, both in the run's results."""
    run = tmp_path / "quick"
    run_cli(["experiment=vlm_quickstart", "data.size=[32,48]", "model.embedded.frame_size=[32,48]",
             "data.train.num_cases=2", "data.val.num_cases=1", "data.batch_size=2", "trainer.max_steps=3",
             "trainer.val_check_interval=2", "trainer.limit_val_batches=1", "task.cases=1",
             "task.illusions=[road_repair]", "task.severities=[3]", "model.max_new_tokens=4", "judge=none",
             "progress=plain", *TINY_PRETRAINING], run)
    assert (run / "model" / "config.json").is_file()
    assert "val/loss" in (run / "csv" / "metrics.csv").read_text()
    answers = ResultsLog(run / "test" / "per_answer.jsonl").records()
    blind = ResultsLog(run / "test" / "blind" / "per_answer.jsonl").records()
    assert len(answers) == len(blind) == ANSWERS and {r["key"] for r in answers} == {r["key"] for r in blind}
    models = {r["model"] for r in answers} | {r["model"] for r in blind}
    assert models == {"embedded-qwen2vl-1.4M", "embedded-qwen2vl-1.4M-blind"}


def test_scene_batches_draw_rendered_variants_with_their_scene_classes_and_need_the_truth(tmp_path):
    """The vision pretraining's batches: every variant of the chosen base clips, each with its own base clip's
    scene classes; a suite on disk (no truth) is refused naming the setting."""
    import numpy as np

    from lanevil_train.tasks.vlm.train import prepare_clips, scene_batches
    from lanevil_train.vlm.clips.clip_set import ClipSetDataset, SyntheticClipSuite, build_clip_set

    suite = SyntheticClipSuite(2, 0, ["road_repair"], severities=[3], size=(32, 48))
    bases = [suite.clip_meta(i)["base_clip_id"] for i in range(0, len(suite), 2)]
    sample = scene_batches(suite, prepare_clips(suite, bases, bases[::2], workers=0, progress="none"), batch=8, seed=0)
    clips, classes = sample(0)
    assert len(clips) == len(classes) == 8 and all(c.shape == (6, 32, 48, 3) and c.dtype == np.uint8 for c in clips)
    by_frames = {suite[i]["frames"][0].tobytes(): suite.scene_classes_for(suite.clip_meta(i)["base_clip_id"])
                 for i in range(len(suite)) if suite.clip_meta(i)["base_clip_id"] in bases[::2]}
    assert all(by_frames[c[0].tobytes()] == k for c, k in zip(clips, classes))
    build_clip_set(suite.cases[:1], [3], tmp_path / "set", size=(32, 48))
    with pytest.raises(ValueError, match="model.embedded.vision_pretraining: .*ClipSetDataset"):
        prepare_clips(ClipSetDataset(tmp_path / "set"), bases, bases, workers=0)
