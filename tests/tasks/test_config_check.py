"""config_check: the user-facing values of every group are checked when the config is composed, each problem
naming its key, what was expected and what was given; every shipped config passes unchanged."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose

import lanevil_train.conf
from lanevil_train.models.backbones import TESTED_BACKBONES, stage_strides
from lanevil_train.tasks.config_check import ConfigError, check_config
from tests.tasks.cli_helpers import REPO, TINY

CONF = Path(lanevil_train.conf.__file__).parent
GROUPS = ("data", "model", "backbone", "defense", "task", "trainer", "callbacks", "logger", "experiment",
          "hparams_search", "judge")


pytestmark = pytest.mark.usefixtures("hydra_conf")  # tests/conftest.py


@pytest.fixture
def files(tmp_path):
    """A file, a directory, and an illusion set directory (holding manifest.jsonl), none of them read."""
    (tmp_path / "model.ckpt").write_bytes(b"")
    (tmp_path / "dataset").mkdir()
    (tmp_path / "set").mkdir()
    (tmp_path / "set" / "manifest.jsonl").write_text("")
    return tmp_path


def problems(*overrides: str) -> list[str]:
    """check_config's problems on the root config composed with `overrides` (none: [])."""
    try:
        check_config(compose(config_name="config", overrides=list(overrides)))
    except ConfigError as error:
        assert str(error).splitlines()[1:] == [f"  {p}" for p in error.problems]  # one line each
        return error.problems
    return []


def only_problem(*overrides: str) -> str:
    found = problems(*overrides)
    assert len(found) == 1, found
    return found[0]


# ------------------------------------------------------------------------------------------- shipped configs

def shipped_options() -> list[tuple[str, str]]:
    return [(group, path.relative_to(CONF / group).with_suffix("").as_posix())
            for group in GROUPS for path in sorted((CONF / group).rglob("*.yaml"))]


def needs(group: str, option: str, files: Path) -> list[str]:
    """What an option needs from the user by design: a dataset root (???), a checkpoint to score."""
    if group == "experiment" and option.startswith("official_laneatt_"):  # and the repository's anchor counts
        return [f"data.root={files / 'dataset'}", f"model.head.anchor_frequency_file={files / 'model.ckpt'}"]
    if (group == "data" and option in ("tusimple", "culane", "llamas", "curvelanes")) or \
            (group == "experiment" and option.startswith(("paper_", "official_"))):
        return [f"data.root={files / 'dataset'}"]
    if group == "task" and option == "audit_qa":  # the QA file to audit
        return ["task.suite=synthetic"]
    if group == "task" and option in ("evaluate", "cross_domain", "closed_loop", "search"):
        return [f"ckpt_path={files / 'model.ckpt'}"]
    if group == "backbone" and option == "dla34":  # its trees add maps that a size of no multiple of 32 misaligns:
        return ["data.input_size=[192,320]"]      # the default data's [180, 320] is refused (a size it takes named)
    if group == "model" and option == "vlm/hf":
        return ["task=evaluate", f"model.path={files / 'dataset'}"]
    if group == "model" and option == "vlm/embedded":
        return []  # task=train (the default) builds and trains it on the clip suite, which it selects
    if group == "model" and option == "vlm/openai":
        return ["task=evaluate", "model.base_url=http://127.0.0.1:8000/v1", "model.name=some-vlm"]
    if group == "judge" and option == "openai":  # and an API key in OPENAI_API_KEY (the test sets one)
        return ["judge.base_url=http://127.0.0.1:8000/v1", "judge.model=some-llm"]
    return []


def test_every_group_has_shipped_options():
    options = shipped_options()
    assert {group for group, _ in options} == set(GROUPS)
    assert len(options) > 35


@pytest.mark.parametrize("group, option", shipped_options(), ids=lambda value: str(value))
def test_every_shipped_option_passes(group, option, files, monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", "a-key")
    assert problems(f"{group}={option}", *needs(group, option, files)) == []


def test_pat_plus_plus_settings_are_checked_naming_the_key(files):
    assert only_problem("defense=pat++", "defense.alpha=1.5").startswith("defense.alpha: expected a number")
    assert only_problem("defense=pat++", "defense.hard_target=answer").startswith(
        "defense.hard_target: expected one of goal, goal_then_answer, got 'answer'")
    assert only_problem("defense=pat++", "defense.top_k=0").startswith("defense.top_k: expected an integer")
    assert only_problem("defense=pat++", f"defense.prefix_path={files / 'none.json'}").startswith(
        "defense.prefix_path: expected null or the path of an existing prefix.json file")
    assert problems("defense=pat++", f"defense.prefix_path={files / 'model.ckpt'}") == []


@pytest.mark.parametrize("extra", [[], ["task=compare"], ["task=evaluate", "ckpt_path=FILE"], ["defense=aam++"],
                                   ["backbone=vgg16"], ["trainer=ddp"], ["hparams_search=aam_optuna"]],
                         ids=lambda value: " ".join(value) or "alone")
def test_quickstart_passes_with_other_groups(extra, files):
    extra = [e.replace("FILE", str(files / "model.ckpt")) for e in extra]
    assert problems("experiment=quickstart", *extra) == []


def test_the_test_suites_tiny_config_passes():
    assert problems(*TINY) == []


def test_build_on_a_real_dataset_may_take_every_image(files):
    assert problems("task=build", "data=tusimple", f"data.root={files / 'dataset'}", "task.cases=0") == []


# ------------------------------------------------------------------------------------------- each group
DEFENSES = "task.defenses: expected a list of defense config names, each once, with none and at least one other"

BAD = [
    # root
    (["seed=-1"], "seed: expected an integer from 0 to 4294967295, got -1"),
    (["seed=abc"], "seed: expected an integer from 0 to 4294967295, got 'abc'"),
    (["ckpt_path=/no/such/last.ckpt"],
     "ckpt_path: expected null or the path of an existing checkpoint file, got '/no/such/last.ckpt' (no such file)"),
    (["progress=fancy"], "progress: expected one of auto, rich, tqdm, plain, none, got 'fancy'"),
    # data
    (["data.input_size=[112]"], "data.input_size: expected [height, width], two integers >= 16, got [112]"),
    (["data.input_size=[112,8]"], "data.input_size: expected [height, width], two integers >= 16, got [112, 8]"),
    (["data.input_size=[112.5,320]"],
     "data.input_size: expected [height, width], two integers >= 16, got [112.5, 320]"),
    (["data.input_size=[24,320]"],
     "data.input_size: expected [height, width], both >= 32, got [24, 320]: the head reads the stride-32 "
     "feature map of resnet18 (backbone.out_indices [4]), which must have at least one row and one column"),
    (["data.batch_size=-1"], "data.batch_size: expected an integer >= 1, got -1"),
    (["data.batch_size=2.5"], "data.batch_size: expected an integer >= 1, got 2.5"),
    (["data.num_workers=-1"], "data.num_workers: expected an integer >= 0, got -1"),
    (["data.crop_top=1.0"], "data.crop_top: expected a number in [0, 1), got 1.0"),
    (["data.crop_top=half"], "data.crop_top: expected a number in [0, 1), got 'half'"),
    (["data.normalize=caffe"], "data.normalize: expected one of imagenet, laneatt, clrnet, ganet, got 'caffe'"),
    (["data.resize=bicubic"], "data.resize: expected one of area, linear, cubic, pil_bilinear, got 'bicubic'"),
    (["data.augment=maybe"], "data.augment: expected true or false, got 'maybe'"),
    (["data.max_lanes=0"], "data.max_lanes: expected an integer >= 1, got 0"),
    (["data.train.num_scenes=0"], "data.train.num_scenes: expected an integer >= 1, got 0"),
    (["data.val.first_seed=-5"], "data.val.first_seed: expected an integer >= 0, got -5"),
    (["data.test.size=[720]"], "data.test.size: expected [height, width], two integers >= 16, got [720]"),
    (["data.train.cache=1"], "data.train.cache: expected true or false, got 1"),
    (["data=tusimple", "data.root=/no/such/tusimple"],
     "data.root: expected the path of an existing dataset directory, got '/no/such/tusimple' (no such directory)"),
    (["data=culane"], "data.root: is not set (??? in the config); set it to the path of an existing dataset "
                      "directory: data.root=..."),
    (["data.train_transforms=[{p: 0.3}]"],
     "data.train_transforms: expected null or a list of mappings, each with a _target_ (e.g. [{_target_: "
     "lanevil_train.illusions.IllusionTransform, p: 0.3}]), got [{p: 0.3}]"),
    (["data.train_transforms=[{_target_: lanevil_train.illusions.NoSuchTransform}]"],
     "data.train_transforms[0]._target_: cannot import 'lanevil_train.illusions.NoSuchTransform' "
     "(AttributeError: module 'lanevil_train.illusions' has no attribute 'NoSuchTransform')"),
    (["data.train._target_=no_such_package.Dataset"],
     "data.train._target_: cannot import 'no_such_package.Dataset' (ModuleNotFoundError: No module named "
     "'no_such_package')"),
    (["+data.train.num_scene=3"],
     "data.train.num_scene: not a parameter of lanevil_train.data.datasets.SyntheticLaneDataset; did you mean "
     "data.train.num_scenes? it accepts num_scenes, first_seed, size, cache"),
    # model
    (["model.head.n_offsets=1"], "model.head.n_offsets: expected an integer >= 2, got 1"),
    (["model.head.topk_anchors=1"], "model.head.topk_anchors: expected null or an integer >= 2, got 1"),
    (["model.head.lateral_n=0"], "model.head.lateral_n: expected null or an integer >= 1, got 0"),
    (["model.head.max_lanes=0"], "model.head.max_lanes: expected an integer >= 1, got 0"),
    (["+model.head.focal_alpha=2"], "model.head.focal_alpha: expected a number in [0, 1], got 2"),
    (["+model.head.in_channels=3"],
     "model.head.in_channels: is set by the code (from the backbone and data.input_size); remove it"),
    (["+model.head.n_offset=3"],
     "model.head.n_offset: not a parameter of lanevil_train.models.laneatt.LaneATTHead; did you mean "
     "model.head.n_offsets? it accepts in_channels"),
    (["model.optimizer.lr=0"], "model.optimizer.lr: expected a number > 0, got 0"),
    (["model.optimizer.lr=1e-3x"], "model.optimizer.lr: expected a number > 0, got '1e-3x'"),
    (["model.optimizer.weight_decay=-0.1"], "model.optimizer.weight_decay: expected a number >= 0, got -0.1"),
    (["model.scheduler=step"],
     "model.scheduler: expected null or a mapping with a _target_ (the dotted name of a class or function), "
     "got 'step'"),
    (["model.scheduler._target_=torch.optim.NoSuchSchedule"],
     "model.scheduler._target_: cannot import 'torch.optim.NoSuchSchedule'"),
    (["+model.optimizer.momentum=0.9"],
     "model.optimizer.momentum: not a parameter of torch.optim.Adam; it accepts params, lr"),
    (["model=ufld", "model.head.slot_assignment=middle"],
     "model.head.slot_assignment: expected one of ego, packed, got 'middle'"),
    (["model=clrnet", "model.head.num_priors=0"], "model.head.num_priors: expected an integer >= 1, got 0"),
    (["model=scnn", "model.decode.exist_threshold=2"],
     "model.decode.exist_threshold: expected a number in [0, 1], got 2"),
    (["model=clrnet", "+model.decode.min_points=3"],
     "model.decode.min_points: not a decoding option of CLRNetHead; it takes conf_threshold, nms_threshold, nms_topk"),
    (["model.lr_scaling=quadratic"], "model.lr_scaling: expected one of linear, sqrt, none, got 'quadratic'"),
    (["+model.lr_multipliers={backbone.*:-1}"],
     "model.lr_multipliers: expected null or a mapping {parameter name pattern: rate factor >= 0}"),
    (["+model.gradient_clip_norm=0"], "model.gradient_clip_norm: expected null or a number > 0, got 0"),
    (["model.reference_batch_size=0"], "model.reference_batch_size: expected null or an integer >= 1, got 0"),
    (["model.output_stride=4"], "model.output_stride: expected null or one of 8, 16, 32, got 4"),
    (["model.feature_strides=[64]"],
     "model.feature_strides: backbone resnet18 (output_stride=None) has no stage of stride 64; its stages have "
     "strides [2, 4, 8, 16, 32] (set backbone.out_indices to choose the stages)"),
    (["+model.neck.in_strides=[8]"], "model.neck: expected null or a mapping with a _target_"),
    (["model.decode.conf_threshold=1.5"], "model.decode.conf_threshold: expected a number in [0, 1], got 1.5"),
    (["model.decode.nms_threshold=-1"], "model.decode.nms_threshold: expected a number >= 0, got -1"),
    (["model.decode.nms_topk=0"], "model.decode.nms_topk: expected null or an integer >= 1, got 0"),
    # simulated splits are disjoint seed ranges
    (["data.test.first_seed=10"],
     "data.test.first_seed: the test split's seeds [10, 210) overlap the train split's [0, 2000); splits must not "
     "share scenes"),
    (["data=clips", "data.test.first_seed=1500"],
     "data.test.first_seed: the test split's seeds [1500, 1600) overlap the train split's [0, 2000)"),
    # model=vlm/<backend>
    (["task=evaluate", "model=vlm/hf"],
     "model.path: is not set (??? in the config); set it to null or the path of an existing directory of a saved "
     "Hugging Face model (save_pretrained): model.path=..."),
    (["task=evaluate", "model=vlm/hf", "model.path=/no/such/model"],
     "model.path: expected null or the path of an existing directory of a saved Hugging Face model "
     "(save_pretrained), got '/no/such/model' (no such directory)"),
    (["task=evaluate", "model=vlm/openai", "model.base_url=localhost:8000", "model.name=m"],
     "model.base_url: expected an http(s) URL, e.g. http://127.0.0.1:8000/v1, got 'localhost:8000'"),
    (["task=evaluate", "model=vlm/openai", "model.base_url=http://h/v1", "model.name=m", "model.concurrency=0"],
     "model.concurrency: expected an integer >= 1, got 0"),
    (["task=train", "model=vlm/openai", "model.base_url=http://h/v1", "model.name=m"],
     "task: task=train with model=lanevil_train.vlm.backends.openai.OpenAIVLM: a model behind a server cannot be "
     "trained here; fine-tune a local one"),
    # the kind of model decides the task's function (tasks/kinds.py)
    (["task=export", "model=vlm/openai", "model.base_url=http://h/v1", "model.name=m"],
     "task: task=export runs detector models; this model is a vlm (model.kind=vlm)"),
    (["~model.kind"], "model.kind: expected one of detector, vlm (a lane detector's conf/model/<family>.yaml says "
     "`kind: detector`, a VLM backend's conf/model/vlm/<backend>.yaml `kind: vlm`), got None"),
    (["model.kind=detectr"], "model.kind: expected one of detector, vlm"),
    (["task=train", "model=vlm/hf", "model.path=/tmp", "data=synthetic"],
     "data: expected clips (a VLM trains on the clip suite's QA), got 'synthetic' (model=vlm/<backend> selects "
     "data=clips unless another data= is given: drop it)"),
    (["task=evaluate", "model=vlm/hf", "model.path=null"],
     "model.path: the model is loaded from a folder: give ckpt_path=<a task=train run's checkpoint> or model.path="),
    (["task=train", "data=clips", "model=vlm/hf", "model.path=/tmp", "model.lora.r=0"],
     "model.lora.r: expected an integer >= 1, got 0"),
    (["task=train", "data=clips", "model=vlm/hf", "model.path=/tmp", "model.fine_tune.variants=some"],
     "model.fine_tune.variants: expected one of clean, all, got 'some'"),
    (["task=evaluate", "model=vlm/openai", "model.base_url=http://h/v1", "model.name=m", "+model.top_p=0.9"],
     "model.top_p: not a parameter of lanevil_train.vlm.backends.openai.OpenAIVLM; it accepts base_url"),
    (["task=evaluate", "model=vlm/openai", "model.base_url=http://h/v1", "model.name=m", "judge=openai",
      "judge.model=gpt-4o-mini", "judge.api_key_env=null"],
     "judge.base_url: is not set (??? in the config); set it to an http(s) URL, e.g. http://127.0.0.1:8000/v1: "
     "judge.base_url=..."),
    # an API key variable that is not set: named before the first request (and before any other work)
    (["task=evaluate", "model=vlm/openai", "model.base_url=http://h/v1", "model.name=m",
      "model.api_key_env=LANEVIL_UNSET_TEST_KEY"],
     "model.api_key_env: expected null (no key sent) or the name of a set environment variable holding the API key, "
     "got 'LANEVIL_UNSET_TEST_KEY' (the environment variable LANEVIL_UNSET_TEST_KEY is not set; export "
     "LANEVIL_UNSET_TEST_KEY=<the key>, or set api_key_env to null for a server that takes no key)"),
    (["task=evaluate", "model=vlm/openai", "model.base_url=http://h/v1", "model.name=m", "judge=openai",
      "judge.base_url=http://h/v1", "judge.model=j", "judge.api_key_env=LANEVIL_UNSET_TEST_KEY"],
     "judge.api_key_env: expected null (no key sent) or the name of a set environment variable holding the API key, "
     "got 'LANEVIL_UNSET_TEST_KEY' (the environment variable LANEVIL_UNSET_TEST_KEY is not set"),
    # backbone
    (["backbone.name=resnet9"], "backbone.name: expected a timm model name (resnet18, resnet34, resnet50, resnet101, "
     "vgg16, ...), got 'resnet9'"),
    (["backbone.pretrained=yes"], "backbone.pretrained: expected true or false, got 'yes'"),
    (["backbone.checkpoint=/no/such/weights.pth"],
     "backbone.checkpoint: expected null or the path of an existing state dict file, got '/no/such/weights.pth' "
     "(no such file)"),
    (["backbone.out_indices=[5]"],
     "backbone.out_indices: expected stage indices of resnet18 from 0 to 4 (strides 2, 4, 8, 16, 32), got [5]"),
    (["backbone.out_indices=[]"], "backbone.out_indices: expected null or a non-empty list of integers, got []"),
    (["backbone=vgg16", "backbone.out_indices=[5]", "data.input_size=[24,320]"],
     "data.input_size: expected [height, width], both >= 32, got [24, 320]: the head reads the stride-32 "
     "feature map of vgg16 (backbone.out_indices [5])"),
    (["experiment=quickstart", "backbone.name=eva02_tiny_patch14_224", "backbone.out_indices=[11]"],
     "backbone.name: eva02_tiny_patch14_224 cannot take data.input_size=[112, 320]: timm's eva02_tiny_patch14_224 "
     "fails on a 112x320 input (Input width (320) should be divisible by patch size (14).); it takes "
     "data.input_size=[112,322]"),
    # defense
    (["+defense.callbacks=[]"],
     "defense: expected a mapping with the keys name, transforms, mixer, callback (and, in a textual defense"),
    (["defense=aam++", "+defense.callback.t_hha=0.5"],
     "defense.callback.t_hha: not a parameter of lanevil_train.callbacks.AttentionAreaMixing; did you mean "
     "defense.callback.t_haa? it accepts layer, mode"),
    (["defense=mixup", "defense.mixer._target_=lanevil_train.data.mixers.MixDown"],
     "defense.mixer._target_: cannot import 'lanevil_train.data.mixers.MixDown' (AttributeError"),
    (["defense=cutout", "defense.transforms=[{p: 0.5}]"],
     "defense.transforms: expected null or a list of mappings, each with a _target_"),
    (["defense=cutout", "+defense.transforms.0.holes=2"],
     "defense.transforms[0].holes: not a parameter of lanevil_train.data.defenses.LaneCutout; did you mean "
     "defense.transforms[0].num_holes? it accepts num_holes, hole_height, hole_width, fill, p"),
    (["defense=pgd", "defense.callback=3"],
     "defense.callback: expected null or a mapping with a _target_ (the dotted name of a class or function), "
     "got 3"),
    # task
    (["task.severities=[0,6]"], "task.severities: expected a non-empty list of integers from 1 to 5, got [0, 6]"),
    (["task.severities=[]"], "task.severities: expected a non-empty list of integers from 1 to 5, got []"),
    (["task.illusions=[smoke,vehicle]"],
     "task.illusions: expected 'all' or a non-empty list of illusion (or, for a corruption suite, corruption) names, "
     "got ['smoke', 'vehicle'] (unknown: smoke; known: illusions road_crack, road_repair"),
    (["task.illusions=some"], "task.illusions: expected 'all' or a non-empty list of illusion (or, for a corruption "
     "suite, corruption) names, got 'some'"),
    (["task.repeats=0"], "task.repeats: expected an integer >= 1, got 0"),
    (["task.cases=-1"], "task.cases: expected an integer >= 0, got -1"),
    (["task.cases=0"], "task.cases: expected an integer >= 1, the number of simulated scenes (0, every image, is "
                       "only for task=build on a real dataset), got 0"),
    (["task.test_after_fit=no"], "task.test_after_fit: expected true or false, got 'no'"),
    (["task.html=no"], "task.html: expected true or false, got 'no'"),
    (["task=report", "task.html=1"], "task.html: expected true or false, got 1"),
    (["task.init_from=/no/such/init.ckpt"],
     "task.init_from: expected null or the path of an existing checkpoint file, got '/no/such/init.ckpt' "
     "(no such file)"),
    (["task.suite=/no/such/set"],
     "task.suite: expected null, synthetic (the illusion suite), corruptions, combined, a directory written by "
     "task=build (holding manifest.jsonl, or clips.jsonl for a VLM), or a DriveLM QA .json file, got "
     "'/no/such/set' (no such directory)"),
    (["task=build", "task.workers=-1"], "task.workers: expected an integer >= 0, got -1"),
    (["task=build", "task.frames=0"], "task.frames: expected an integer >= 1, got 0"),
    (["task=build", "task.frame_step_m=0"], "task.frame_step_m: expected a number > 0, got 0"),
    (["task=build", "task.fallback=1"], "task.fallback: expected true or false, got 1"),
    (["task=build", "task.cases=0"], "task.cases: expected an integer >= 1, the number of simulated scenes"),
    (["task=evaluate"],
     "ckpt_path: task=evaluate scores a checkpoint; expected the path of a Lightning checkpoint file "
     "(or task.onnx=model.onnx), got null"),
    (["task=cross_domain"], "ckpt_path: task=cross_domain scores a checkpoint"),
    (["task=report", "task.runs=[1]"], "task.runs: expected a list of strings, got [1]"),
    (["task=compare", "task.defenses=[none,aam+]"],
     f"{DEFENSES}, got ['none', 'aam+'] (unknown: aam+; known: aam, aam++, copypaste, cutout, hsv, mida, mixup, "
     f"none, pat, pat++, pgd, self_reminder)"),
    (["task=compare", "task.defenses=[aam,aam++]"],
     f"{DEFENSES}, got ['aam', 'aam++'] ('none' is missing: it is the reference every gain is measured against)"),
    (["task=compare", "task.defenses=[none]"], f"{DEFENSES}, got ['none'] (nothing to compare 'none' with)"),
    (["task=compare", "task.defenses=[none,aam,aam]"],
     f"{DEFENSES}, got ['none', 'aam', 'aam'] (a name is listed twice)"),
    (["task=compare", "task.repeats=0"], "task.repeats: expected an integer >= 1, got 0"),
    # trainer
    (["trainer.max_steps=0"], "trainer.max_steps: expected -1 or an integer >= 1, got 0"),
    (["trainer.max_epochs=0"], "trainer.max_epochs: expected null or -1 or an integer >= 1, got 0"),
    (["trainer.max_epochs=-1"], "trainer.max_epochs: -1 together with trainer.max_steps=-1 trains forever"),
    (["trainer.limit_val_batches=1.5"],
     "trainer.limit_val_batches: expected null or an integer >= 0 or a number in [0, 1], got 1.5"),
    (["trainer.limit_train_batches=-1"],
     "trainer.limit_train_batches: expected null or an integer >= 0 or a number in [0, 1], got -1"),
    (["trainer.log_every_n_steps=0"], "trainer.log_every_n_steps: expected an integer >= 1, got 0"),
    (["+trainer.val_check_interval=0.0"],
     "trainer.val_check_interval: expected null or an integer >= 1 or a number in (0, 1], got 0.0"),
    (["trainer.check_val_every_n_epoch=0"],
     "trainer.check_val_every_n_epoch: expected null or an integer >= 1, got 0"),
    (["trainer.gradient_clip_val=-1"], "trainer.gradient_clip_val: expected null or a number >= 0, got -1"),
    # suites of other kinds, seeds and intervals
    (["task.suite=corruptions", "task.illusions=[rail_shadow]"],
     "task.illusions[0]: unknown corruption 'rail_shadow'; the corruptions suite's names: snow, rain, fog"),
    (["task.suite=combined", "task.illusions=[rail_shadow,fence_shadow]"],
     "task.illusions: a combined suite pairs illusions of two categories"),
    (["task=build", "task.kind=weather"], "task.kind: expected one of illusions, corruptions, combined, got 'weather'"),
    (["task=build", "task.kind=corruptions", "task.illusions=[vehicle]"],
     "task.illusions[0]: unknown corruption 'vehicle'"),
    (["task=compare", "task.seeds=[0,1,1]"], "task.seeds: expected a list of distinct integers >= 0"),
    (["task=compare", "task.bootstrap=10"], "task.bootstrap: expected an integer >= 100, got 10"),
    (["task=compare", "task.confidence=1.0"], "task.confidence: expected a number in (0, 1), got 1.0"),
    (["task.suite=smoke"], "task.suite: expected null, synthetic (the illusion suite), corruptions"),
    # callbacks and logger
    (["+callbacks.model_checkpoint.save_every=2"],
     "callbacks.model_checkpoint.save_every: not a parameter of pytorch_lightning.callbacks.ModelCheckpoint; "
     "it accepts dirpath, filename"),
    (["+callbacks.swa._target_=pytorch_lightning.callbacks.NoSuchCallback"],
     "callbacks.swa._target_: cannot import 'pytorch_lightning.callbacks.NoSuchCallback'"),
    (["+callbacks.broken=3"],
     "callbacks.broken: expected null or a mapping with a _target_ (the dotted name of a class or function), got 3"),
    # settings groups a class owns whole: an unknown key named by its dotted path, the nearest setting, all of them
    (["task=closed_loop", "task.policy=truth", "+task.kalman.memry_s=0.3"],
     "task.kalman.memry_s: not a setting of task.kalman; did you mean task.kalman.memory_s? its settings: "
     "offset_sigma_m, slope_sigma, curvature_sigma, point_sigma_m, curvature_rate_sigma, memory_s"),
    (["task=closed_loop", "task.policy=truth", "+task.pure_pursuit.lookahead=1"],
     "task.pure_pursuit.lookahead: not a setting of task.pure_pursuit; did you mean task.pure_pursuit.lookahead_s? "
     "its settings: lookahead_s, min_lookahead_m"),
    (["task=closed_loop", "task.policy=truth", "+task.stanley.k=1"],
     "task.stanley.k: not a setting of task.stanley; its settings: gain, softening_mps"),
    (["task=closed_loop", "task.policy=truth", "+task.mpc.horizon=2"],
     "task.mpc.horizon: not a setting of task.mpc; did you mean task.mpc.horizon_s? its settings: horizon_s, "
     "q_lateral, q_heading, r_steer, r_rate"),
    (["task=closed_loop", "task.policy=truth", "+task.vehicle.speed=30"],
     "task.vehicle.speed: not a setting of task.vehicle; did you mean task.vehicle.speed_mph? its settings: "
     "wheelbase_m, speed_mph, max_steer_deg, max_steer_rate_dps"),
    (["task=closed_loop", "task.policy=truth", "+task.vlm.frame=2"],
     "task.vlm.frame: not a setting of task.vlm; did you mean task.vlm.frames? its settings: question, steer_deg, "
     "frames"),
    (["task=train", "data=clips", "model=vlm/hf", "model.path=/tmp", "+model.lora.rank=8"],
     "model.lora.rank: not a setting of model.lora; its settings: r, alpha, dropout, target_modules"),
    (["task=train", "data=clips", "model=vlm/hf", "model.path=/tmp", "+model.fine_tune.warmup=3"],
     "model.fine_tune.warmup: not a setting of model.fine_tune; did you mean model.fine_tune.warmup_steps? its "
     "settings: lr, weight_decay, warmup_steps"),
    (["+logger.save_every=3"],
     "logger.save_every: not a parameter of pytorch_lightning.loggers.CSVLogger; did you mean logger.save_dir? it "
     "accepts save_dir, name"),
]


@pytest.mark.parametrize("overrides, message", BAD, ids=[" ".join(o) for o, _ in BAD])
def test_a_bad_value_is_named_with_what_was_expected_and_given(overrides, message):
    assert only_problem(*overrides).startswith(message)


def test_a_suite_of_the_other_model_kind_is_named(files):
    (files / "clips").mkdir()
    (files / "clips" / "clips.jsonl").write_text("")
    vlm = ["task=evaluate", "model=vlm/openai", "model.base_url=http://h/v1", "model.name=m"]
    assert only_problem(*vlm, f"task.suite={files / 'set'}") == (
        f"task.suite: expected a clip suite written by task=build data=clips (holding clips.jsonl), synthetic, or a "
        f"DriveLM QA .json file, got '{files / 'set'}' (a VLM answers questions about clips)")
    assert problems(*vlm, f"task.suite={files / 'clips'}") == []
    assert only_problem("task=evaluate", f"ckpt_path={files / 'model.ckpt'}", f"task.suite={files / 'clips'}") == (
        f"task.suite: expected an illusion image set (manifest.jsonl) for a lane detector, got '{files / 'clips'}' "
        f"(that is a VLM clip suite: evaluate it with model=vlm/<backend>)")


def test_paths_of_the_wrong_kind_are_named(files):
    assert only_problem(f"ckpt_path={files}") == \
        f"ckpt_path: expected null or the path of an existing checkpoint file, got '{files}' (a directory, not a file)"
    assert only_problem("data=tusimple", f"data.root={files / 'model.ckpt'}") == \
        (f"data.root: expected the path of an existing dataset directory, got '{files / 'model.ckpt'}' "
         f"(a file, not a directory)")
    assert only_problem(f"task.suite={files / 'dataset'}").endswith("(it holds no manifest.jsonl)")
    assert only_problem("task=build", f"task.out_dir={files / 'model.ckpt'}") == \
        (f"task.out_dir: expected null or a folder path (new, or a folder to resume), got '{files / 'model.ckpt'}' "
         f"(an existing file, not a folder)")
    assert problems(f"task.suite={files / 'set'}", f"task.init_from={files / 'model.ckpt'}",
                    f"backbone.checkpoint={files / 'model.ckpt'}") == []
    assert only_problem("backbone.pretrained=true", f"backbone.checkpoint={files / 'model.ckpt'}") == \
        ("backbone.checkpoint: give either backbone.pretrained=true (timm's download) or "
         "backbone.checkpoint=/path/to/weights.pth, not both")


def test_targets_that_take_any_keyword_accept_any_key():
    assert problems("logger=wandb", "+logger.entity=me", "+data.train_transforms=[{_target_: "
                    "lanevil_train.illusions.IllusionTransform, p: 0.3, anything: 1}]") == []


def test_every_problem_is_reported_at_once_one_per_line():
    with pytest.raises(ConfigError) as caught:
        check_config(compose(config_name="config", overrides=[
            "data.input_size=[112]", "data.batch_size=-1", "model.optimizer.lr=0", "task.severities=[6]",
            "trainer.max_steps=0", "+callbacks.model_checkpoint.nope=1"]))
    lines = str(caught.value).splitlines()
    assert lines[0] == "the config has 6 problems:"
    assert [line.split(":")[0].strip() for line in lines[1:]] == [
        "data.input_size", "data.batch_size", "model.optimizer.lr", "task.severities", "trainer.max_steps",
        "callbacks.model_checkpoint.nope"]
    assert isinstance(caught.value, ValueError)


def test_stage_strides_are_the_built_networks():
    from lanevil_train.models.backbones import build_backbone

    for name in TESTED_BACKBONES:
        expected = (1, 2, 4, 8, 16, 32) if name == "vgg16" else (2, 4, 8, 16, 32)
        assert stage_strides(name) == expected, name
        assert tuple(build_backbone(name, out_indices=None).strides) == expected, name


# ------------------------------------------------------------------------------------------- where it runs

def test_compare_checks_every_runs_config_before_the_first_defense_trains(tmp_path, monkeypatch):
    import lanevil_train.tasks.compare as compare_task

    def run_defense(*args):
        raise AssertionError("a defense started training")

    monkeypatch.setattr(compare_task, "run_defense", run_defense)
    cfg = compose(config_name="config", overrides=["task=compare", "task.defenses=[none,pgd]",
                                                   f"task.out_dir={tmp_path}"])
    with pytest.raises(ConfigError, match=r"the config of the defense=none run has 1 problem:\n"
                                          r"  data.batch_size: expected an integer >= 1, got 0"):
        compare_task.compare(cfg, overrides=["data.batch_size=0"])
    run = compare_task.compose_run(cfg, "pgd", [], tmp_path / "pgd")  # a good run config passes its check
    assert run.defense.name == "pgd"


def test_the_command_line_stops_before_any_work(tmp_path):
    run_dir = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "lanevil_train", "data.input_size=[112]", "data.batch_size=-1",
                           "progress=none", f"hydra.run.dir={run_dir}"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    assert "data.input_size: expected [height, width], two integers >= 16, got [112]" in proc.stderr
    assert "data.batch_size: expected an integer >= 1, got -1" in proc.stderr
    assert not (run_dir / "checkpoints").exists() and not (run_dir / "csv").exists()
    assert not (run_dir / "per_image.jsonl").exists()


def test_a_head_owns_its_parameters_rules_and_the_config_check_reports_them_by_key():
    """One place says what a good head parameter is: the head's SETTINGS, checked by its constructor and, by key,
    before any work by the config check (which keeps no rules of its own for model.head.*)."""
    from lanevil_train.models.scnn import SCNNHead
    from lanevil_train.tasks.config_check import RULES

    assert not [key for key in RULES if key.startswith("model.head.")]
    assert problems("model=scnn", "model.head.dropout=1.0") == \
        ["model.head.dropout: expected a number in [0, 1), got 1.0"]
    with pytest.raises(ValueError, match=r"^model\.head\.dropout: expected a number in \[0, 1\), got 1\.0$"):
        SCNNHead([512], [8], (112, 320), dropout=1.0)
    # a parameter the old flat table did not know: checked now
    assert problems("model=laneformer", "model.head.pixel_attention=maybe") == \
        ["model.head.pixel_attention: expected true or false, got 'maybe'"]


def test_a_textual_defense_owns_its_settings_rules():
    """defense=pat++ / pat / self_reminder: the rules live with the defenses (vlm/defenses/settings.py); the config
    check reads the same rule objects, and a VLM task checks a defense's settings with them before any model loads."""
    from lanevil_train.tasks.config_check import RULES
    from lanevil_train.vlm.defenses.settings import SETTINGS, prompt_problems

    assert all(RULES[f"defense.{key}"] is rule for key, rule in SETTINGS.items())
    good = {"prompt": "pat", "alpha": 0.5, "steps": 3, "prefix_length": 4, "top_k": 8, "num_candidates": 8,
            "chunk": 4, "examples": 2, "pool_clips": 4, "suffix_length": 2}
    assert prompt_problems(good) == []
    assert prompt_problems({**good, "alpha": 2, "steps": 0}) == [
        "defense.alpha: expected a number in [0, 1], got 2", "defense.steps: expected an integer >= 1, got 0"]
    assert prompt_problems({"prompt": "self_reminder", "before": "Be careful."}) == [
        "defense.after: expected a non-empty string, got null"]  # a key the method needs, absent


def test_fine_tuning_owns_its_settings_rules():
    """model.lora.* and model.fine_tune.*: the rules of the fine-tuner and of the clip pairing, read by the config
    check as they are and checked by their owners when built."""
    from lanevil_train.tasks.config_check import RULES
    from lanevil_train.vlm.clips.qa_data import PAIRING_SETTINGS
    from lanevil_train.vlm.training.finetune import FINE_TUNE_SETTINGS, LORA_SETTINGS, check_lora

    assert all(RULES[f"model.lora.{key}"] is rule for key, rule in LORA_SETTINGS.items())
    assert all(RULES[f"model.fine_tune.{key}"] is rule
               for key, rule in {**FINE_TUNE_SETTINGS, **PAIRING_SETTINGS}.items())
    with pytest.raises(ValueError, match=r"^lora\.dropout: expected a number in \[0, 1\), got 1$"):
        check_lora({"dropout": 1})
    assert check_lora({"target_modules": "q_proj"})["target_modules"] == ["q_proj"]
