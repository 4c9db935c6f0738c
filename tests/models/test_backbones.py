import pytest
import timm
import torch

from lanevil_train.models.backbones import TESTED_BACKBONES, build_backbone, indices_for_strides, stage_strides


@pytest.mark.parametrize("name", TESTED_BACKBONES)
def test_every_backbone_builds_offline_and_reports_its_maps(name):
    torch.manual_seed(0)
    net = build_backbone(name).eval()
    with torch.no_grad():
        maps = net(torch.zeros(1, 3, 64, 96))
    assert len(maps) == len(net.channels) == len(net.strides) == 1
    assert maps[0].shape[1] == net.channels[0]
    # timm rounds ResNet sizes up and VGG pools down
    assert maps[0].shape[-1] == 96 // net.strides[0]
    expected_stride = 16 if name == "vgg16" else 32
    assert net.strides == [expected_stride]
    assert net.channels == [512 if name in ("resnet18", "resnet34", "vgg16") else 2048]


def test_unknown_backbone_names_close_timm_models():
    with pytest.raises(ValueError, match="'resnet19': not a timm model name"):
        build_backbone("resnet19")
    with pytest.raises(ValueError, match="close names: .*resnet101"):
        build_backbone("resnet10")


def test_any_timm_backbone_by_name():
    net = build_backbone("mobilenetv3_small_050", out_indices=None).eval()
    with torch.no_grad():
        maps = net(torch.zeros(1, 3, 64, 64))
    assert [m.shape[-1] for m in maps] == [64 // s for s in net.strides]


@pytest.mark.parametrize("name", ["resnet18", "resnet50", "vgg16"])
def test_output_stride_dilates_instead_of_striding(name):
    torch.manual_seed(0)
    plain = build_backbone(name, out_indices=None).eval()
    dilated = build_backbone(name, out_indices=None, output_stride=8).eval()
    assert dilated.strides == [min(s, 8) for s in plain.strides]
    assert list(stage_strides(name, 8)) == dilated.strides
    with torch.no_grad():
        maps = dilated(torch.zeros(1, 3, 64, 96))
    assert [m.shape[-2:] for m in maps][-1] == (8, 12)  # the deepest map at stride 8
    # the same weights: an ImageNet checkpoint of the plain network loads into the dilated one
    assert {k: v.shape for k, v in plain.state_dict().items()} == {k: v.shape for k, v in dilated.state_dict().items()}


def test_feature_strides_pick_the_stages():
    assert indices_for_strides("resnet18", [8, 16, 32]) == (2, 3, 4)
    assert indices_for_strides("vgg16", [16]) == (4,)
    assert indices_for_strides("resnet34", [8], output_stride=8) == (4,)  # the deepest of the stride-8 stages
    with pytest.raises(ValueError, match="no stage of stride 64"):
        indices_for_strides("resnet18", [64])


def test_checkpoint_round_trip_and_wrapped_formats(tmp_path):
    torch.manual_seed(1)
    src = build_backbone("resnet18", out_indices=(2, 4))
    path = tmp_path / "bb.pt"
    # a Lightning-style file with a prefix on every key
    torch.save({"state_dict": {f"model.{k}": v for k, v in src.state_dict().items()}}, path)
    torch.manual_seed(2)
    dst = build_backbone("resnet18", checkpoint=str(path), out_indices=(2, 4))
    for k, v in src.state_dict().items():
        assert torch.equal(v, dst.state_dict()[k]), k
    x = torch.randn(1, 3, 64, 64)
    src.eval(), dst.eval()
    assert all(torch.equal(a, b) for a, b in zip(src(x), dst(x)))


def test_imagenet_style_state_dicts_load(tmp_path):
    # a full timm classifier (with fc) loads into the features-only net, ignoring the head
    torch.manual_seed(3)
    full = timm.create_model("resnet18", pretrained=False)
    path = tmp_path / "imagenet.pth"
    torch.save(full.state_dict(), path)
    net = build_backbone("resnet18", checkpoint=str(path), out_indices=(3,))  # layer4 pruned: ignored too
    assert torch.equal(net.state_dict()["conv1.weight"], full.state_dict()["conv1.weight"])
    # torchvision-style vgg16 keys ("features.0.weight") map onto timm's flattened names
    vgg = timm.create_model("vgg16", pretrained=False)
    path = tmp_path / "vgg.pth"
    torch.save(vgg.state_dict(), path)
    net = build_backbone("vgg16", checkpoint=str(path))
    assert torch.equal(net.state_dict()["features_28.weight"], vgg.state_dict()["features.28.weight"])


def test_bad_checkpoints_raise_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        build_backbone("resnet18", checkpoint=str(tmp_path / "nope.pt"))
    other = build_backbone("resnet34").state_dict()
    path = tmp_path / "r34.pt"
    torch.save(other, path)
    with pytest.raises(ValueError, match=r"r34\.pt.*resnet18.*unexpected keys.*layer1\.2\."):
        build_backbone("resnet18", checkpoint=str(path))
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pt"):
        build_backbone("resnet18", checkpoint=str(junk))


def test_a_vit_is_built_for_the_data_input_size_not_only_its_pretraining_size():
    """timm's ViTs assert their 224x224 pretraining size unless built with dynamic_img_size: built so here, a ViT
    takes the quickstart's 112x320 (a 7x20 patch grid), and the check before work finds nothing to say."""
    from lanevil_train.models.backbones import input_size_problem

    net = build_backbone("vit_tiny_patch16_224", out_indices=(11,)).eval()
    with torch.no_grad():
        maps = net(torch.zeros(1, 3, 112, 320))
    assert [tuple(m.shape) for m in maps] == [(1, 192, 7, 20)] and net.strides == [16]
    assert input_size_problem("vit_tiny_patch16_224", (112, 320), (11,)) is None
    assert input_size_problem("resnet18", (112, 320), (4,)) is None


def test_a_backbone_that_cannot_take_the_input_size_is_named_with_a_size_it_takes():
    """A forward pass on the meta device (no weights) finds what would fail at the first training step: a patch
    size that does not divide the input (with the size rounded up to it, which works), DLA's trees on a size that is
    no multiple of 32, feature maps channels last (Swin's), which no head reads."""
    from lanevil_train.models.backbones import input_size_problem

    assert input_size_problem("eva02_tiny_patch14_224", (112, 320), (11,)) == (
        "timm's eva02_tiny_patch14_224 fails on a 112x320 input (Input width (320) should be divisible by patch size "
        "(14).); it takes data.input_size=[112,322] (multiples of its stride 14)")
    assert input_size_problem("eva02_tiny_patch14_224", (112, 322), (11,)) is None
    dla = input_size_problem("dla34", (360, 640))
    assert dla.startswith("timm's dla34 fails on a 360x640 input (") and dla.endswith(
        "; it takes data.input_size=[384,640] (multiples of its stride 32)"), dla
    assert input_size_problem("dla34", (384, 640)) is None
    swin = input_size_problem("swin_tiny_patch4_window7_224", (112, 320))
    assert swin.startswith("timm's swin_tiny_patch4_window7_224 gives its feature maps as (1, 28, 80, 96), not "
                           "(N, C, H, W) with C = 96 (channels last"), swin


@pytest.mark.parametrize("name", ["resnet18", "vgg16"])
def test_inference_max_pools_give_the_plain_pools_values_exactly(name):
    """Without autograd the backbone's max-pools pool a channels-last copy (4x faster on a CPU): the feature maps
    must equal those of timm's own nn.MaxPool2d to the bit, and with autograd on the plain module runs."""
    from lanevil_train.models.backbones import ChannelsLastMaxPool2d

    torch.manual_seed(0)
    net = build_backbone(name, out_indices=None).eval()
    pools = [m for m in net.modules() if isinstance(m, torch.nn.MaxPool2d)]
    assert pools and all(type(m) is ChannelsLastMaxPool2d for m in pools)
    torch.manual_seed(0)
    plain = timm.create_model(name, features_only=True, out_indices=None if name != "vgg16" else (0, 1, 2, 3, 4, 5))
    plain.load_state_dict(net.state_dict())  # the same keys: the pools hold no weights
    plain.eval()
    image = torch.randn(2, 3, 67, 101)  # odd sizes: the padding and ceil_mode edges
    with torch.no_grad():
        fast, reference = net(image), plain(image)
    assert len(fast) == len(reference)
    for ours, theirs in zip(fast, reference):
        assert ours.is_contiguous() and torch.equal(ours, theirs)
    # with autograd the values (and so the gradients' routes) are nn.MaxPool2d's own
    pool = pools[0]
    x = torch.randn(1, 4, 9, 11, requires_grad=True)
    y = pool(x)
    expected = torch.nn.functional.max_pool2d(x, pool.kernel_size, pool.stride, pool.padding, pool.dilation,
                                              ceil_mode=pool.ceil_mode)
    assert torch.equal(y, expected) and y.requires_grad
