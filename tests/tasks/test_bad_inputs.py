"""Bad inputs found before any long work: empty splits, unreadable checkpoints, each error naming its key and file.

Every test here fails if `Trainer.fit` is reached: the mistake must be reported before a training step runs.
"""

from __future__ import annotations

import os

import pytest
import pytorch_lightning as pl
import torch
from hydra import compose, initialize_config_module

from lanevil_train.checkpoints import CheckpointError
from lanevil_train.data.datasets import EmptySplitError
from lanevil_train.data.formats import write_culane, write_tusimple
from lanevil_train.tasks.build import build
from lanevil_train.tasks.builders import build_model, model_config
from lanevil_train.tasks.detector.evaluate import evaluate
from lanevil_train.tasks.detector.train import train
from lanevil_train.tasks.kinds import task_function
from tests.tasks.cli_helpers import TINY, composed, write_photo_dataset


@pytest.fixture(autouse=True)
def no_training(monkeypatch):
    def fit(*args, **kwargs):
        raise AssertionError("Trainer.fit ran: the bad input was not found before training")

    monkeypatch.setattr(pl.Trainer, "fit", fit)


def _config(tmp_path, *overrides):
    """The tiny test config with `overrides`; the simulated-scene settings only when no other data= (or an
    experiment's) is chosen."""
    tiny = TINY if not any(o.startswith(("data=", "experiment=")) for o in overrides) else \
        [o for o in TINY if not o.startswith(("data.train.", "data.val.", "data.test."))]
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        return compose(config_name="config",
                       overrides=[*tiny, "logger=none", f"output_dir={tmp_path / 'run'}", *overrides])


def _tusimple(tmp_path, train_lines: int, test_lines: int):
    root = tmp_path / "tusimple"
    records = write_photo_dataset(root, [f"clips/{i}/20.jpg" for i in range(4)])
    write_tusimple(records[:train_lines], root / "train.json")
    write_tusimple(records[2:2 + test_lines], root / "test.json")
    return root, ["data=tusimple", f"data.root={root}", "data.num_workers=0", "data.input_size=[64,160]",
                  "data.train.label_files=[train.json]", "data.val.label_files=[train.json]",
                  "data.test.label_files=[test.json]"]


@pytest.mark.parametrize("split", ["train", "test"])
def test_an_empty_tusimple_split_is_refused_before_training(tmp_path, split):
    root, data = _tusimple(tmp_path, train_lines=0 if split == "train" else 2, test_lines=0 if split == "test" else 2)
    with pytest.raises(EmptySplitError) as error:
        train(_config(tmp_path, *data))
    message = str(error.value)
    assert message.startswith(f"data.{split}.label_files: the {split} split is empty")
    assert str(root / f"{split}.json") in message and "list no images" in message


def test_an_empty_culane_list_is_refused_before_training(tmp_path):
    root = tmp_path / "culane"
    records = write_photo_dataset(root, [f"d/v.MP4/{i:05d}.jpg" for i in range(2)])
    write_culane(records, root, root / "list" / "train_gt.txt")
    (root / "list" / "test.txt").write_text("\n")  # a blank line only
    cfg = _config(tmp_path, "data=culane", f"data.root={root}", "data.num_workers=0", "data.input_size=[64,160]",
                  "data.val.list_file=list/train_gt.txt")
    with pytest.raises(EmptySplitError, match=r"^data\.test\.list_file: the test split is empty: the CULane list "
                                              rf"file {root / 'list' / 'test.txt'} lists no images"):
        train(cfg)


def test_zero_simulated_scenes_name_the_key(tmp_path):
    with pytest.raises(EmptySplitError, match=r"^data\.val\.num_scenes: the val split is empty: .*got 0"):
        train(_config(tmp_path, "data.val.num_scenes=0"))


def test_an_empty_illusion_suite_is_refused_before_training(tmp_path):
    suite = tmp_path / "set"
    suite.mkdir()
    (suite / "manifest.jsonl").write_text("")
    (suite / "labels.json").write_text("")
    with pytest.raises(EmptySplitError, match=rf"^task\.suite={suite}: the illusion set's manifest .*lists no images"):
        train(_config(tmp_path, f"task.suite={suite}"))


def test_build_refuses_an_empty_source(tmp_path):
    root, data = _tusimple(tmp_path, train_lines=2, test_lines=0)
    out = tmp_path / "set"
    with pytest.raises(EmptySplitError, match=rf"^data\.test\.label_files: the test split is empty: "
                                              rf".*{root / 'test.json'}"):
        build(_config(tmp_path, "task=build", f"task.out_dir={out}", *data))
    assert not out.exists()
    with pytest.raises(ValueError, match=r"^task\.cases: .*>= 1, got 0"):
        build(_config(tmp_path, "task=build", f"task.out_dir={out}", "task.cases=0"))
    assert not out.exists()


# -- checkpoints ----------------------------------------------------------------------------------------------------

class Unsafe:
    """A class torch.load(weights_only=True) refuses to unpickle."""


def _bad_checkpoint(tmp_path, kind: str):
    """A file that is not a readable checkpoint: random bytes, a real checkpoint cut in half, or a pickled object."""
    path = tmp_path / f"{kind}.ckpt"
    if kind == "random":
        path.write_bytes(os.urandom(4096))
    elif kind == "truncated":
        model = build_model(model_config(_config(tmp_path)))
        torch.save({"state_dict": model.state_dict(), "global_step": 3}, path)
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:  # a checkpoint holding a pickled Python object: refused, never loaded unsafely
        torch.save({"state_dict": {}, "extra": Unsafe()}, path)
    return path


REASONS = {"random": "not a readable checkpoint: its content is not a torch.save file",
           "truncated": "not a readable checkpoint: it is truncated",
           "object": "not a plain weights file: it holds pickled Python objects that weights-only loading will not "
                     "run (tests.tasks.test_bad_inputs.Unsafe)"}


def _assert_refused(error, option: str, path, kind: str) -> None:
    message = str(error.value)
    assert message.startswith(f"{option}={path}: {REASONS[kind]}"), message
    assert "weights_only" not in message and error.value.__cause__ is None  # torch's unsafe advice is not passed on


@pytest.mark.parametrize("kind", ["random", "truncated", "object"])
def test_evaluate_ckpt_path_that_is_not_a_checkpoint(tmp_path, kind):
    path = _bad_checkpoint(tmp_path, kind)
    with pytest.raises(CheckpointError) as error:
        evaluate(_config(tmp_path, "task=evaluate", f"ckpt_path={path}"))
    _assert_refused(error, "ckpt_path", path, kind)


@pytest.mark.parametrize("option", ["ckpt_path", "task.init_from"])
@pytest.mark.parametrize("kind", ["random", "truncated"])
def test_train_checkpoint_options_that_are_not_checkpoints(tmp_path, option, kind):
    path = _bad_checkpoint(tmp_path, kind)
    with pytest.raises(CheckpointError) as error:
        train(_config(tmp_path, f"{option}={path}"))
    _assert_refused(error, option, path, kind)


@pytest.mark.parametrize("kind", ["random", "truncated"])
def test_backbone_checkpoint_that_is_not_a_checkpoint(tmp_path, kind):
    path = _bad_checkpoint(tmp_path, kind)
    with pytest.raises(CheckpointError) as error:
        train(_config(tmp_path, f"backbone.checkpoint={path}"))
    _assert_refused(error, "backbone.checkpoint", path, kind)


def test_a_checkpoint_of_another_network_names_the_option(tmp_path):
    path = tmp_path / "r34.ckpt"
    model = build_model(model_config(_config(tmp_path, "backbone=resnet34")))
    torch.save({"state_dict": model.state_dict()}, path)
    with pytest.raises(CheckpointError, match=rf"^task\.init_from={path}: its weights do not fit this run's network "
                                              r".*: weights 96 unexpected \(first: backbone\.layer1\.2\.conv1\.weight"):
        train(_config(tmp_path, f"task.init_from={path}"))


def test_an_empty_checkpoint_file(tmp_path):
    path = tmp_path / "empty.ckpt"
    path.write_bytes(b"")
    with pytest.raises(CheckpointError, match=rf"^ckpt_path={path}: not a readable checkpoint: the file is empty"):
        train(_config(tmp_path, f"ckpt_path={path}"))


def test_trainer_arguments_lightning_refuses_are_reported_before_the_data_is_read(tmp_path, monkeypatch):
    import lanevil_train.tasks.detector.train as train_module

    def no_data(*args, **kwargs):
        raise AssertionError("the datasets were read before the trainer's arguments were checked")

    monkeypatch.setattr(train_module, "build_datamodule", no_data)
    with pytest.raises(ValueError, match=r"^trainer: Lightning refused the trainer\.\* arguments: .*devices=0"):
        train(_config(tmp_path, "trainer.devices=0"))


def test_resuming_with_another_input_geometry_is_refused(tmp_path):
    cfg = _config(tmp_path)
    model = build_model(model_config(cfg))
    path = tmp_path / "last.ckpt"
    torch.save({"state_dict": model.state_dict(), "lanevil_model": model.build_config}, path)
    with pytest.raises(ValueError, match=rf"^ckpt_path={path}: resuming needs the network the checkpoint was trained "
                                         r"with, and this config differs \(data\.crop_top was 0\.0, now 0\.4\); .*"
                                         rf"task\.init_from={path}"):
        train(_config(tmp_path, f"ckpt_path={path}", "data.crop_top=0.4"))


# --------------------------------------------------------------------------------------- a checkpoint of the other kind

@pytest.fixture(scope="module")
def vlm_checkpoints(tmp_path_factory):
    """Checkpoints of two VLM fine-tuning runs as Lightning writes them (the module's state dict and hparams): one
    tuned from a Hugging Face folder, one from the embedded VLM a run builds into its init/ folder."""
    import shutil

    from lanevil_dev.tiny_vlm import build_tiny_vlm
    from lanevil_train.vlm.training.finetune import VLMFineTuner

    root = tmp_path_factory.mktemp("vlm_runs")
    hf = build_tiny_vlm("qwen2_vl", root / "tiny-qwen2-vl")
    embedded = shutil.copytree(hf, root / "run" / "init")
    paths = {}
    for name, model_dir in (("hf", hf), ("embedded", embedded)):
        module = VLMFineTuner(str(model_dir), lora={"r": 2, "alpha": 4, "dropout": 0.0})
        paths[name] = root / f"{name}.ckpt"
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams), "global_step": 3},
                   paths[name])
    return {"hf": (paths["hf"], hf), "embedded": (paths["embedded"], embedded)}


@pytest.mark.parametrize("task, option", [("task=evaluate", "ckpt_path"), ("task=closed_loop", "ckpt_path"),
                                          ("task=train", "task.init_from")])
def test_a_vlm_checkpoint_given_to_a_detector_task_names_the_model_it_needs(tmp_path, vlm_checkpoints, task, option):
    from lanevil_train.tasks.closed_loop import closed_loop

    run = {"task=evaluate": evaluate, "task=closed_loop": closed_loop, "task=train": train}[task]
    path, model_dir = vlm_checkpoints["hf"]
    with pytest.raises(CheckpointError) as caught:
        run(_config(tmp_path, task, f"{option}={path}", "task.cases=1"))
    assert str(caught.value) == (f"{option}={path}: a VLM's checkpoint (qwen2_vl fine-tuned from {model_dir}), not "
                                 f"a lane detector's; give it with model=vlm/hf model.path={model_dir}")
    path, model_dir = vlm_checkpoints["embedded"]
    with pytest.raises(CheckpointError, match=rf"^{option}={path}: a VLM's checkpoint \(qwen2_vl fine-tuned from "
                                              rf"{model_dir}\), not a lane detector's; "
                                              r"give it with model=vlm/embedded$"):
        run(_config(tmp_path, task, f"{option}={path}", "task.cases=1"))


def test_a_detector_checkpoint_of_another_family_or_given_to_a_vlm_is_named(tmp_path, vlm_checkpoints):
    ufld = build_model(model_config(_config(tmp_path, "model=ufld")))
    path = tmp_path / "ufld.ckpt"
    torch.save({"state_dict": ufld.state_dict(), "lanevil_model": ufld.build_config}, path)
    for option in ("task.init_from", "ckpt_path"):
        with pytest.raises(CheckpointError, match=rf"^{option}={path}: a ufld-resnet18 checkpoint, and this run builds "
                                                  r"laneatt-resnet18; use model=ufld backbone=resnet18$"):
            train(_config(tmp_path, f"{option}={path}"))
    _, model_dir = vlm_checkpoints["hf"]
    for task in ("task=evaluate", "task=train"):
        with pytest.raises(CheckpointError, match=rf"^ckpt_path={path}: a lane detector's checkpoint "
                                                  r"\(ufld-resnet18\), "
                                                  r"not a VLM's; drop model=vlm/\.\.\.: detector tasks rebuild "
                                                  r"model=ufld backbone=resnet18 from it$"):
            cfg = composed([task, "model=vlm/hf", f"model.path={model_dir}", f"ckpt_path={path}",
                            "data.train.num_cases=1", "task.cases=1", "logger=none", f"output_dir={tmp_path / 'run'}"])
            task_function(cfg)(cfg)  # the task's function for a VLM, as run_task picks it


# ------------------------------------------------------------------------------- a file whose pickle would run code

class RunsCode:
    """Pickled as a call of os.system (posix.system): unpickling it would touch the marker file."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _tiny(overrides: list[str]) -> list[str]:
    """TINY, without the simulated splits' sizes when an experiment chooses another dataset."""
    if any(o.startswith("experiment=") for o in overrides):
        return [o for o in TINY if not o.startswith(("data.train.", "data.val.", "data.test."))]
    return TINY


def _code_running_file(tmp_path, legacy: bool):
    marker = tmp_path / "MARKER"
    path = tmp_path / f"weights_{'legacy' if legacy else 'zip'}.pt"
    torch.save({"state_dict": {"w": torch.zeros(2)}, "payload": RunsCode(marker)}, path,
               _use_new_zipfile_serialization=not legacy)
    return path, marker


# every entry point that reads a torch file: (overrides with FILE for the file, the option the message names)
TORCH_FILE_OPTIONS = {
    "evaluate official": (["task=evaluate", "experiment=official_ufld_tusimple", "backbone=resnet18",
                           "data.root=ROOT", "ckpt_path=FILE"], "ckpt_path"),
    "closed_loop": (["task=closed_loop", "task.cases=1", "ckpt_path=FILE"], "ckpt_path"),
    "closed_loop models": (["task=closed_loop", "task.cases=1", "+task.models={a: FILE}"], "ckpt_path"),
    "export": (["task=export", "ckpt_path=FILE"], "ckpt_path"),
    "train resume": (["ckpt_path=FILE"], "ckpt_path"),
    "train init_from": (["task.init_from=FILE"], "task.init_from"),
    "backbone": (["backbone.checkpoint=FILE"], "backbone.checkpoint"),
    "anchor frequencies": (["model.head.topk_anchors=10", "+model.head.anchor_frequency_file=FILE"],
                           "model.head.anchor_frequency_file"),
}


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy"])
@pytest.mark.parametrize("entry", list(TORCH_FILE_OPTIONS))
def test_a_file_that_would_run_code_is_named_for_what_it_is(tmp_path, entry, legacy):
    """The refusal says what the file is (pickled objects, the first named), not that it is corrupt; the code in it
    never runs (its marker file never appears), in either torch.save format, at every option that reads a torch
    file."""
    from tests.tasks.cli_helpers import run_in_process

    path, marker = _code_running_file(tmp_path, legacy)
    overrides, option = TORCH_FILE_OPTIONS[entry]
    overrides = [o.replace("FILE", str(path)).replace("ROOT", str(tmp_path)) for o in overrides]
    with pytest.raises(CheckpointError) as caught:
        run_in_process([*_tiny(overrides), "logger=none", *overrides], tmp_path / "run")
    message = str(caught.value)
    assert message.startswith(f"{option}={path}: not a plain weights file: it holds pickled Python objects that "
                              f"weights-only loading will not run (posix.system); loading it any other way executes "
                              f"code from whoever made the file"), message
    assert "corrupt" not in message and "weights_only" not in message
    assert not marker.exists()


def test_a_vlm_checkpoint_option_names_a_file_that_would_run_code(tmp_path, vlm_checkpoints):
    _, model_dir = vlm_checkpoints["hf"]
    path, marker = _code_running_file(tmp_path, legacy=False)
    with pytest.raises(CheckpointError, match=rf"^ckpt_path={path}: not a plain weights file: .*\(posix\.system\)"):
        cfg = composed(["task=evaluate", "model=vlm/hf", f"model.path={model_dir}", f"ckpt_path={path}",
                        "task.cases=1", "logger=none", f"output_dir={tmp_path / 'run'}"])
        task_function(cfg)(cfg)
    assert not marker.exists()


def test_the_globals_are_read_from_either_format_and_any_protocol(tmp_path):
    """What the file's pickles import, read with pickletools: GLOBAL (protocol 2, torch's default) and STACK_GLOBAL
    (protocols 4 and 5) alike; a plain checkpoint imports only what weights-only loading rebuilds."""
    import io

    from lanevil_train.files.pickles import objects_not_loaded, pickled_globals

    for protocol in (2, 4, 5):
        for legacy in (False, True):
            buffer = io.BytesIO()
            torch.save({"w": torch.zeros(2), "x": RunsCode(tmp_path / "MARKER")}, buffer, pickle_protocol=protocol,
                       _use_new_zipfile_serialization=not legacy)
            assert objects_not_loaded(buffer.getvalue()) == ["posix.system"], (protocol, legacy)
    model = build_model(model_config(_config(tmp_path)))
    plain = tmp_path / "plain.ckpt"
    torch.save({"state_dict": model.state_dict(), "lanevil_model": model.build_config, "epoch": 1}, plain)
    assert "torch._utils._rebuild_tensor_v2" in pickled_globals(plain) and objects_not_loaded(plain) == []
    assert not (tmp_path / "MARKER").exists()


# ------------------------------------------------------------------------------------ release archives and layouts

# the official TuSimple network with 4 grid cells instead of 100: the same keys and layout at a tenth of the 185 MB
# (its classifier's last layer has 101 x 56 x 4 outputs), which each archive test saves several times and reads back
SMALL_UFLD = ["model.head.num_cells=4"]


def _official_ufld(tmp_path, overrides=SMALL_UFLD):
    """The official names of the official_ufld_tusimple network's weights (models/ufld/official.py, inverted)."""
    cfg = composed(["experiment=official_ufld_tusimple", "backbone=resnet18", *overrides])
    model = build_model(model_config(cfg))
    return {("model." + k[len("backbone."):] if k.startswith("backbone.") else k[len("head."):]): v
            for k, v in model.state_dict().items()}, model


def _release_zip(path, experiments: dict[str, list[int]], weights) -> None:
    """A zip as LaneATT publishes its experiments: experiments/<name>/models/model_<epoch>.pt, each a dict with the
    weights under 'model', beside the experiment's config.yaml."""
    import io
    import zipfile

    with zipfile.ZipFile(path, "w") as archive:
        for name, epochs in experiments.items():
            archive.writestr(f"experiments/{name}/config.yaml", "model: {}\n")
            for epoch in epochs:
                buffer = io.BytesIO()
                torch.save({"epoch": epoch, "model": {k: v + epoch for k, v in weights.items()},
                            "optimizer": {"state": {}, "param_groups": []}}, buffer)
                archive.writestr(f"experiments/{name}/models/model_{epoch:04d}.pt", buffer.getvalue())


def _loaded(tmp_path, ckpt_path: str):
    """The network task=evaluate builds for experiment=official_ufld_tusimple from ckpt_path (its first weight)."""
    from lanevil_train.tasks.builders import checkpoint_model

    return checkpoint_model(composed(["task=evaluate", "experiment=official_ufld_tusimple", "backbone=resnet18",
                                      *SMALL_UFLD, f"data.root={tmp_path}", f"ckpt_path={ckpt_path}"]))


def test_a_release_archive_is_read_at_its_last_epoch_or_the_named_member(tmp_path, caplog):
    import logging

    from lanevil_train.tasks.config_check import check_config

    weights, _ = _official_ufld(tmp_path)
    release = tmp_path / "ufld_experiments.zip"
    _release_zip(release, {"ufld_r18_tusimple": [5, 100, 20]}, weights)
    first = "model.conv1.weight"
    with caplog.at_level(logging.INFO, logger="lanevil_train"):
        model = _loaded(tmp_path, str(release))
    assert torch.equal(model.state_dict()["backbone.conv1.weight"], weights[first] + 100)  # the last epoch
    assert (f"ckpt_path={release}: a release archive (experiments/ufld_r18_tusimple); reading "
            f"experiments/ufld_r18_tusimple/models/model_0100.pt, the last of its 3 checkpoints") in caplog.text
    named = f"{release}::models/model_0020.pt"  # the end of a member's name is enough
    check_config(composed(["task=evaluate", "experiment=official_ufld_tusimple", f"data.root={tmp_path}",
                           f"ckpt_path={named}"]))  # the config check takes ARCHIVE::member
    assert torch.equal(_loaded(tmp_path, named).state_dict()["backbone.conv1.weight"], weights[first] + 20)
    with pytest.raises(CheckpointError, match=rf"^ckpt_path={release}: a checkpoint inside an archive cannot be "
                                              rf"resumed .*task\.init_from={release}$"):
        train(_config(tmp_path, f"ckpt_path={release}"))
    with pytest.raises(CheckpointError, match=rf"^ckpt_path={release}::models/model_0007\.pt: no member of that name; "
                                              r"its checkpoints: experiments/ufld_r18_tusimple/models/model_0005\.pt"):
        _loaded(tmp_path, f"{release}::models/model_0007.pt")


def test_a_release_archive_of_several_experiments_or_none_is_refused_naming_what_is_inside(tmp_path):
    import zipfile

    weights, _ = _official_ufld(tmp_path)
    release = tmp_path / "laneatt_experiments.zip"
    _release_zip(release, {"laneatt_r18_tusimple": [100], "laneatt_r34_culane": [15]}, weights)
    with pytest.raises(CheckpointError, match=rf"^ckpt_path={release}: a release archive of 2 experiments "
                                              r"\(experiments/laneatt_r18_tusimple, experiments/laneatt_r34_culane\); "
                                              rf"name the checkpoint to read: ckpt_path={release}::experiments/"):
        _loaded(tmp_path, str(release))
    papers = tmp_path / "papers.zip"
    with zipfile.ZipFile(papers, "w") as archive:
        archive.writestr("readme.txt", "no weights here")
    with pytest.raises(CheckpointError, match=rf"^ckpt_path={papers}: a zip archive that is neither a torch\.save "
                                              r"file nor a release holding checkpoints .*; it holds readme\.txt"):
        _loaded(tmp_path, str(papers))


def test_a_plain_script_checkpoint_and_a_bare_state_dict_load_and_other_layouts_are_listed(tmp_path):
    weights, reference = _official_ufld(tmp_path)
    script = tmp_path / "script.pt"  # what plain PyTorch training scripts save
    torch.save({"epoch": 7, "model_state_dict": weights, "optimizer_state_dict": {"state": {}}}, script)
    assert torch.equal(_loaded(tmp_path, str(script)).state_dict()["head.cls.2.weight"], weights["cls.2.weight"])
    bare = tmp_path / "ours.pt"  # this project's own names, saved with torch.save(model.state_dict(), path)
    torch.save(reference.state_dict(), bare)
    assert torch.equal(_loaded(tmp_path, str(bare)).state_dict()["head.cls.2.weight"], weights["cls.2.weight"])
    other = tmp_path / "other.pt"
    torch.save({"weights": weights, "epoch": 7}, other)
    with pytest.raises(CheckpointError, match=rf"^ckpt_path={other}: a dict whose top-level keys are weights, epoch: "
                                              r"none of the checkpoint layouts this project reads \(a Lightning "
                                              r"checkpoint .*'model_state_dict'.*a bare state dict"):
        _loaded(tmp_path, str(other))
    with pytest.raises(CheckpointError, match=rf"^ckpt_path={script}: a file of weights alone .* holds no training "
                                              rf"state to resume; .*task\.init_from={script}$"):
        train(_config(tmp_path, f"ckpt_path={script}"))


# ----------------------------------------------------------------------------------------------- smaller messages

def test_an_official_file_that_does_not_fit_the_run_it_names_says_a_setting_on_top_changes_it(tmp_path):
    """The file's release is the very experiment and backbone this run has, but data.input_size on top of it
    changes the network: the message says so, rather than only advising the command already run."""
    from lanevil_train.tasks.builders import checkpoint_model

    weights, _ = _official_ufld(tmp_path, overrides=[])  # the release's own shapes
    path = tmp_path / "tusimple_18.pth"
    torch.save({"model": weights}, path)
    with pytest.raises(CheckpointError) as caught:
        checkpoint_model(composed(["task=evaluate", "experiment=official_ufld_tusimple", "backbone=resnet18",
                                   "data.input_size=[144,400]", f"ckpt_path={path}"]))
    message = str(caught.value)
    assert "head.cls.0.weight (2048, 1800) vs (2048, 520)" in message, message  # 5 x 13 cells x 8 channels
    assert message.endswith("(the tusimple release, resnet18: 100 cells, 56 row anchors, 4 lanes): run it with "
                            "experiment=official_ufld_tusimple backbone=resnet18, whose network has its shapes; if "
                            "this run is that already, a setting given on top of it (data.input_size, "
                            "data.max_lanes, model.head.*) changes the network: drop it"), message


def test_an_anchor_frequency_file_of_another_anchor_set_names_the_file(tmp_path):
    path = tmp_path / "tusimple_anchors_freq.pt"
    torch.save(torch.ones(2782), path)
    with pytest.raises(ValueError, match=rf"^model\.head\.anchor_frequency_file={path}: 2782 counts, and this head "
                                         r"has \d+ anchors \(n_offsets 72, lateral_n None, bottom_n None at 64x160, "
                                         r"data\.input_size\): the file was counted for another anchor set"):
        build_model(model_config(_config(tmp_path, "model.head.topk_anchors=10",
                                         f"+model.head.anchor_frequency_file={path}")))
