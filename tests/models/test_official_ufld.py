"""The published UFLD v1 files load as the official code saved them: the network in the official layout (written
here from the facts in models/ufld/official.py, torchvision's ResNet under `model.`) and ours, given the converted
file, compute the same outputs; files of another family or release are refused naming the config that fits."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torchvision
from torch import nn

from lanevil_train.checkpoints import CheckpointError
from lanevil_train.models.official import load_detector_weights, official_state_dict, recognise
from lanevil_train.tasks.builders import build_model, checkpoint_model, model_config
from tests.tasks.cli_helpers import composed

CULANE = (200, 18)  # cells, rows of the CULane release (a smaller classifier than TuSimple's 100 x 56)


class ConvBnRelu(nn.Module):
    """The official conv_bn_relu block: attributes conv, bn (and a ReLU)."""

    def __init__(self, cin, cout, dilation=1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, padding=dilation, dilation=dilation, bias=False)
        self.bn = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU()

    def forward(self, x):
        return self.relu(self.bn(self.conv(x)))


class OfficialLayout(nn.Module):
    """UFLD v1's parsingNet as its file lays it out: model.{conv1, bn1, layer1-4} (torchvision ResNet-18), pool (1x1
    to 8), cls (Linear 1800-2048, ReLU, Linear), output viewed (cells + 1, rows, 4); with aux, aux_header2/3/4 and
    aux_combine."""

    def __init__(self, cells, rows, aux=False):
        super().__init__()
        resnet = torchvision.models.resnet18()
        self.model = nn.Module()
        for name in ("conv1", "bn1", "relu", "maxpool", "layer1", "layer2", "layer3", "layer4"):
            setattr(self.model, name, getattr(resnet, name))
        self.shape = (cells + 1, rows, 4)
        self.pool = nn.Conv2d(512, 8, 1)
        self.cls = nn.Sequential(nn.Linear(1800, 2048), nn.ReLU(), nn.Linear(2048, (cells + 1) * rows * 4))
        if aux:
            self.aux_header2 = nn.Sequential(*[ConvBnRelu(128 if i == 0 else 128, 128) for i in range(4)])
            self.aux_header3 = nn.Sequential(ConvBnRelu(256, 128), ConvBnRelu(128, 128), ConvBnRelu(128, 128))
            self.aux_header4 = nn.Sequential(ConvBnRelu(512, 128), ConvBnRelu(128, 128))
            self.aux_combine = nn.Sequential(ConvBnRelu(384, 256, 2), ConvBnRelu(256, 128, 2), ConvBnRelu(128, 128, 2),
                                             ConvBnRelu(128, 128, 4), nn.Conv2d(128, 5, 1))
        for p in self.parameters():  # away from the initial values, so a weight left unloaded shows
            nn.init.normal_(p, 0.0, 0.02)

    def features(self, x):
        m = self.model
        x = m.layer1(m.maxpool(m.relu(m.bn1(m.conv1(x)))))
        x2 = m.layer2(x)
        x3 = m.layer3(x2)
        return x2, x3, m.layer4(x3)

    def forward(self, x):
        fea = self.features(x)[-1]
        return self.cls(self.pool(fea).view(-1, 1800)).view(-1, *self.shape)

    def aux_seg(self, x):
        x2, x3, x4 = self.features(x)
        up = nn.functional.interpolate
        maps = [self.aux_header2(x2), up(self.aux_header3(x3), scale_factor=2, mode="bilinear"),
                up(self.aux_header4(x4), scale_factor=4, mode="bilinear")]
        return self.aux_combine(torch.cat(maps, dim=1))


def _official_file(path, net, prefix="module."):
    """Saved as the official training saves it: {'model': state dict (DataParallel's prefix), 'optimizer': ...}."""
    torch.save({"model": {prefix + k: v for k, v in net.state_dict().items()}, "optimizer": {"state": {}}}, path)
    return path


def _ours(experiment, *overrides):
    cfg = composed([f"experiment={experiment}", "data.root=/unused", *overrides])
    return build_model(model_config(cfg)).eval(), cfg


@pytest.fixture(scope="module")
def culane_file(tmp_path_factory):
    torch.manual_seed(0)
    net = OfficialLayout(*CULANE, aux=True).eval()
    return net, _official_file(tmp_path_factory.mktemp("official") / "culane_18.pth", net)


def test_the_converted_file_gives_the_official_networks_outputs(culane_file):
    official, path = culane_file
    model, _ = _ours("official_ufld_culane")
    line = load_detector_weights(model, path, "task.init_from")
    assert "official UFLD v1" in line and "culane release, resnet18: 200 cells, 18 row anchors, 4 lanes" in line
    x = torch.randn(1, 3, 288, 800)
    with torch.no_grad():
        expected = official(x)
        got = model(x)["cls_logits"]
    assert got.shape == expected.shape == (1, 201, 18, 4)
    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-4)


def test_the_auxiliary_branch_converts_too_and_is_optional(culane_file):
    official, path = culane_file
    model, _ = _ours("official_ufld_culane", "model.head.use_aux=true")
    load_detector_weights(model, path, "task.init_from")
    x = torch.randn(1, 3, 288, 800)
    with torch.no_grad():
        torch.testing.assert_close(model.head.aux(model.features(x)), official.aux_seg(x), rtol=1e-4, atol=1e-4)

    # a published file without the branch, into a network with one: the branch keeps its initial weights
    torch.manual_seed(1)
    bare = OfficialLayout(*CULANE, aux=False)
    fresh, _ = _ours("official_ufld_culane", "model.head.use_aux=true")
    before = {k: v.clone() for k, v in fresh.state_dict().items() if k.startswith("head.aux.")}
    load_detector_weights(fresh, _official_file(path.parent / "bare.pth", bare, prefix=""), "task.init_from")
    after = fresh.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    torch.testing.assert_close(after["head.pool.weight"], bare.pool.weight)


def test_release_and_backbone_are_recognised_from_keys_and_shapes(culane_file):
    _, path = culane_file
    state = official_state_dict(torch.load(path, weights_only=True))
    assert next(iter(state)).startswith("model.")  # 'module.' dropped
    release, found = recognise(state)
    assert release.family == "ufld"
    assert found.config == "experiment=official_ufld_culane backbone=resnet18"


def test_a_file_of_another_release_is_refused_naming_the_weight_and_the_config(culane_file):
    _, path = culane_file
    model, _ = _ours("official_ufld_tusimple")
    with pytest.raises(CheckpointError) as error:
        load_detector_weights(model, path, "ckpt_path")
    message = str(error.value)
    assert "head.cls.2.weight (14472, 2048) vs (22624, 2048)" in message
    assert "run it with experiment=official_ufld_culane backbone=resnet18" in message


def test_a_file_of_another_family_is_refused_naming_the_config_that_fits(culane_file):
    _, path = culane_file
    cfg = composed(["task=evaluate", "model=laneatt", f"ckpt_path={path}", "data.input_size=[64,160]"])
    with pytest.raises(CheckpointError, match="an official UFLD v1 .* this run builds model=laneatt; run it with "
                                              "experiment=official_ufld_culane backbone=resnet18"):
        checkpoint_model(cfg)


def test_a_file_of_no_known_release_names_its_first_weight(tmp_path):
    path = tmp_path / "other.pth"
    torch.save({"net": {"module.backbone.stem.weight": torch.zeros(3, 3)}}, path)
    cfg = composed(["task=evaluate", f"ckpt_path={path}", "data.input_size=[64,160]"])
    known = r"\(BezierLaneNet .*, CLRNet .*, LaneATT .*, SCNN .*, UFLD v1 .*\)"
    with pytest.raises(CheckpointError, match=rf"nor an official one of a release it reads {known}; its first weight "
                                              rf"is backbone.stem.weight \(3, 3\)"):
        checkpoint_model(cfg)


def test_checkpoint_model_builds_the_configs_network_for_an_official_file(culane_file):
    official, path = culane_file
    cfg = composed(["task=evaluate", "experiment=official_ufld_culane", "data.root=/unused", f"ckpt_path={path}"])
    model = checkpoint_model(cfg).eval()
    x = torch.randn(1, 3, 288, 800)
    with torch.no_grad():
        torch.testing.assert_close(model(x)["cls_logits"], official(x), rtol=1e-4, atol=1e-4)


def test_resuming_an_official_file_is_refused_pointing_to_init_from(culane_file, tmp_path):
    from lanevil_train.tasks.detector.train import train

    _, path = culane_file
    cfg = composed([f"ckpt_path={path}", f"output_dir={tmp_path}", "data.input_size=[64,160]"])
    with pytest.raises(CheckpointError, match=f"holds no training state to resume; start a run from its weights with "
                                              f"task.init_from={path}"):
        train(cfg)


def test_task_evaluate_scores_an_official_file_on_a_culane_folder(culane_file, tmp_path):
    """`python -m lanevil_train task=evaluate experiment=official_ufld_culane ckpt_path=culane_18.pth data.root=R`,
    in this process: the config check passes, the file is converted, the images scored and the files written."""
    from lanevil_train.data.formats import write_culane
    from tests.tasks.cli_helpers import run_in_process, write_photo_dataset

    _, path = culane_file
    root = tmp_path / "culane"
    names = [f"driver_00_01frame/05151640_0419.MP4/{i:05d}.jpg" for i in range(2)]
    write_culane(write_photo_dataset(root, names), root, root / "list" / "test.txt")
    run_dir = tmp_path / "run"
    run_in_process(["task=evaluate", "experiment=official_ufld_culane", f"data.root={root}", f"ckpt_path={path}",
                    "trainer=cpu", "progress=none", "data.num_workers=0", "task.predictions=true"], run_dir)
    assert (run_dir / "test_scores.json").is_file()
    listed = (run_dir / "predictions" / "culane" / "list.txt").read_text().split()
    assert listed == ["/" + name for name in names]


def test_task_train_starts_from_an_official_file_with_init_from(culane_file, tmp_path, caplog):
    """Fine-tuning a published model (the paper's MIDA use): `task=train task.init_from=culane_18.pth` converts the
    file (its log line), then trains from it (one step here, on a tiny CULane folder)."""
    import logging

    from lanevil_train.data.formats import write_culane
    from tests.tasks.cli_helpers import run_in_process, write_photo_dataset

    _, path = culane_file
    root = tmp_path / "culane"
    names = [f"driver_00_01frame/05151640_0419.MP4/{i:05d}.jpg" for i in range(2)]
    records = write_photo_dataset(root, names)
    for split in ("train_gt", "val", "test"):
        write_culane(records, root, root / "list" / f"{split}.txt")
    with caplog.at_level(logging.INFO):
        run_in_process(["experiment=official_ufld_culane", f"data.root={root}", f"task.init_from={path}",
                        "data.val.list_file=list/val.txt", "trainer=cpu", "trainer.fast_dev_run=true",
                        "task.test_after_fit=false", "progress=none", "data.num_workers=0", "data.batch_size=2"],
                       tmp_path / "run")
    assert f"task.init_from={path}: official UFLD v1 (cfzd/Ultra-Fast-Lane-Detection) checkpoint (the culane " \
           f"release, resnet18" in caplog.text


def test_load_detector_recognises_an_official_file_and_predicts_as_the_evaluation(culane_file):
    """`load_detector(path)` with no settings: the file is recognised (the CULane release, ResNet-18), its
    experiment's network built and the weights converted; its lanes on a 1640x590 frame are those of the network
    task=evaluate builds for the file, fed as the evaluation feeds it (its sample processor, predict_lanes)."""
    import cv2

    from lanevil_train.models.factory import load_detector

    official, path = culane_file
    det = load_detector(path)
    assert det.build_config["model"]["name"] == "ufld" and det.build_config["input_size"] == [288, 800]
    x = torch.randn(1, 3, 288, 800)
    with torch.no_grad():
        torch.testing.assert_close(det(x)["cls_logits"], official(x), rtol=1e-4, atol=1e-4)
    cfg = composed(["task=evaluate", "experiment=official_ufld_culane", "data.root=/unused", f"ckpt_path={path}"])
    evaluated = checkpoint_model(cfg).eval()
    frame = np.full((590, 1640, 3), 90, np.uint8)
    cv2.line(frame, (400, 589), (780, 250), (235, 235, 235), 12)
    cv2.line(frame, (1300, 589), (880, 250), (235, 235, 235), 12)
    item = evaluated.preprocessor.sample_processor()({"image": frame[:, :, ::-1].copy(), "lanes": [], "meta": {}})
    with torch.no_grad():
        expected = evaluated.predict_lanes(torch.from_numpy(item["image"])[None], [(590, 1640)])[0]
    predicted = det.predict(frame)
    assert len(predicted) == len(expected) > 0
    for lane, points in zip(predicted, expected):
        np.testing.assert_allclose(lane.points, points)
