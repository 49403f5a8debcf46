"""Stage A: stride, crop semantics, output shape, pre-ReLU output, weight loading."""

import cv2
import numpy as np
import pytest
import torch

from neoslam_stream.algorithms import features as F
from neoslam_stream.algorithms.errors import InvalidInput
from neoslam_stream.algorithms.frontend import FrontEnd
from neoslam_stream.nodes.frontend import make_node
from neoslam_stream.runtime.messages import Message


def a_node(**features):
    """Stage A's node with these features parameters."""
    return make_node("features", features=features)


@pytest.fixture(scope="module")
def rand_fx():
    return F.VisualFeatureExtractor(backbone="random_alexnet", seed=1)


def test_stride_keeps_0_s_2s(rand_fx):
    fe = FrontEnd(features={"backbone": "random_alexnet", "frame_stride": 4})
    assert [f for f in range(13) if fe.keep(f)] == [0, 4, 8, 12]


def test_crop_x_is_columns_y_is_rows():
    fx = F.VisualFeatureExtractor(backbone="random_alexnet", crop_image=True, x_min=2, x_max=5, y_min=1, y_max=3)
    img = np.arange(6 * 8).reshape(6, 8)  # 6 rows, 8 columns
    out = fx.crop_array(img)
    assert out.shape == (2, 3)  # rows [1,3), columns [2,5)
    assert out[0, 0] == img[1, 2] and out[-1, -1] == img[2, 4]


def test_crop_disabled_leaves_image_whole():
    fx = F.VisualFeatureExtractor(backbone="random_alexnet", crop_image=False, x_min=2, x_max=5)
    img = np.zeros((6, 8))
    assert fx.crop_array(img).shape == (6, 8)


def test_crop_outside_image_is_a_clear_error():
    fx = F.VisualFeatureExtractor(backbone="random_alexnet", crop_image=True, x_min=0, x_max=100)
    with pytest.raises(F.InvalidImage, match="does not fit"):
        fx.crop_array(np.zeros((10, 20, 3), np.uint8))
    # the node turns it into a counted bad input of that frame
    node = a_node(backbone="random_alexnet", crop_image=True, x_min=0, x_max=100)
    node.setup()
    with pytest.raises(InvalidInput, match="does not fit"):
        node.process("image", Message("image", 0, 0.0, {"image": np.zeros((10, 20, 3), np.uint8)}))


def test_output_is_conv3_pre_relu_64896(rand_fx):
    img = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    f = rand_fx.extract(img)
    assert f.shape == (384 * 13 * 13,) and f.dtype == np.float32
    assert (f < 0).any() and (f > 0).any()  # before the ReLU: negatives exist


def test_channel_major_flattening_matches_the_network(rand_fx):
    img = np.random.default_rng(1).integers(0, 256, (100, 100, 3), dtype=np.uint8)
    x = torch.from_numpy(rand_fx.preprocess(img))[None]
    with torch.no_grad():
        y = rand_fx.net(x)[0].numpy()  # (384, 13, 13)
    f = rand_fx.extract(img)
    c, h, w = 7, 5, 11
    assert f[c * 169 + h * 13 + w] == pytest.approx(y[c, h, w], rel=1e-5, abs=1e-6)


def test_grey_mode_copies_grey_into_three_channels(rand_fx):
    img = np.random.default_rng(2).integers(0, 256, (50, 60, 3), dtype=np.uint8)
    x = rand_fx.preprocess(img)
    # after per-channel normalisation, undoing it must give identical channels
    raw = x * F.IMAGENET_STD[:, None, None] + F.IMAGENET_MEAN[:, None, None]
    np.testing.assert_allclose(raw[0], raw[1], atol=1e-6)
    np.testing.assert_allclose(raw[1], raw[2], atol=1e-6)


def _preprocess_by_definition(rgb: np.ndarray, grey: bool, side: int = 256, crop: int = 224) -> np.ndarray:
    """The paper's preprocessing written out: grey copied into three channels, shorter side to 256
    (bilinear), the centre 224 x 224, scaled to [0, 1] and normalised per channel, channels first
    (``side`` and ``crop`` for another input size)."""
    import cv2

    img = rgb
    if grey:
        img = np.repeat(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[:, :, None], 3, axis=2)
    h, w = img.shape[:2]
    nh, nw = max(side, round(h * side / min(h, w))), max(side, round(w * side / min(h, w)))
    img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_LINEAR)
    top, left = (nh - crop) // 2, (nw - crop) // 2
    img = img[top:top + crop, left:left + crop].astype(np.float32) / 255.0
    return np.ascontiguousarray(((img - F.IMAGENET_MEAN) / F.IMAGENET_STD).transpose(2, 0, 1))


@pytest.mark.parametrize("colour", ["grey", "rgb"])
def test_preprocessing_gives_the_definition_bit_for_bit(colour):
    # grey frames go through the resize as one channel, then fill the three: the same numbers
    fx = F.VisualFeatureExtractor.__new__(F.VisualFeatureExtractor)
    fx.config = F.FeatureConfig(colour=colour)
    rng = np.random.default_rng(5)
    for h, w in [(240, 416), (120, 160), (480, 640), (300, 257), (224, 224), (50, 60)]:
        img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        got = fx.preprocess(img)
        assert got.shape == (3, 224, 224) and got.dtype == np.float32 and got.flags.c_contiguous
        assert np.array_equal(got, _preprocess_by_definition(img, colour == "grey")), (colour, h, w)


@pytest.mark.parametrize(("size", "side"), [(160, 183), (192, 219), (128, 146)])
def test_another_input_size_scales_the_resize_and_the_crop(size, side):
    # input_size S: the shorter side to round(S * 256 / 224) (hand-computed here), the centre S x S
    fx = F.VisualFeatureExtractor.__new__(F.VisualFeatureExtractor)
    fx.config = F.FeatureConfig(input_size=size)
    rng = np.random.default_rng(6)
    for h, w in [(240, 416), (120, 160), (50, 60)]:
        img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        got = fx.preprocess(img)
        assert got.shape == (3, size, size)
        assert np.array_equal(got, _preprocess_by_definition(img, True, side, size)), (size, h, w)


@pytest.mark.parametrize("backbone", ["efficientnet_lite0", "random_alexnet"])
@pytest.mark.parametrize("size", [224, 192, 160, 128, 100])
def test_feature_dim_is_what_the_network_gives(backbone, size):
    # the formula's length equals the network's output on a frame of that size (AlexNet's 64896 and
    # EfficientNet-Lite0's 21952 at 224); the extractor's frozen trace takes the same size
    fx = F.VisualFeatureExtractor(backbone=backbone, device="cpu", input_size=size)
    assert fx.output_dim == F.feature_dim(fx.backbone, size)
    img = np.random.default_rng(size).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    assert fx.extract(img).shape == (fx.output_dim,)
    with torch.no_grad():
        assert fx.module(torch.zeros(1, 3, size, size)).numel() == fx.output_dim
    if size == 224:
        assert fx.output_dim == {"efficientnet_lite0": 112 * 14 * 14, "random_alexnet": 384 * 13 * 13}[backbone]
    if size == 128:  # the default's: 128 -> 64 -> 32 -> 16 -> 8 (EfficientNet); (128 + 4 - 11) // 4 + 1 = 31 -> 15 -> 7
        assert fx.output_dim == {"efficientnet_lite0": 112 * 8 * 8, "random_alexnet": 384 * 7 * 7}[backbone]


def _torchvision_state(seed=0):
    g = torch.Generator().manual_seed(seed)
    shapes = {"features.0": (64, 3, 11, 11), "features.3": (192, 64, 5, 5), "features.6": (384, 192, 3, 3),
              "features.8": (256, 384, 3, 3), "features.10": (256, 256, 3, 3),
              "classifier.1": (4096, 9216), "classifier.4": (4096, 4096), "classifier.6": (1000, 4096)}
    state = {}
    for name, shp in shapes.items():
        if name.startswith("classifier"):
            shp = (8, 8)  # small: their content is irrelevant, their presence is what matters
        state[f"{name}.weight"] = torch.randn(shp, generator=g) * 0.01
        state[f"{name}.bias"] = torch.randn(shp[0], generator=g) * 0.01
    return state


def test_loads_torchvision_state_dict_from_path(tmp_path):
    state = _torchvision_state()
    path = tmp_path / "alexnet-owt-7be5be79.pth"
    torch.save(state, path)
    fx = F.VisualFeatureExtractor(backbone="alexnet", weights_path=str(path))
    assert fx.backbone == "alexnet"
    torch.testing.assert_close(fx.module.conv2.weight, state["features.3.weight"])
    # the first output value equals a hand computation of conv3(pool(relu(conv2(...))))
    img = np.full((64, 64, 3), 128, np.uint8)
    x = torch.from_numpy(fx.preprocess(img))[None]
    nn = torch.nn.functional
    y = nn.max_pool2d(torch.relu(nn.conv2d(x, state["features.0.weight"], state["features.0.bias"], 4, 2)), 3, 2)
    y = nn.max_pool2d(torch.relu(nn.conv2d(y, state["features.3.weight"], state["features.3.bias"], 1, 2)), 3, 2)
    y = nn.conv2d(y, state["features.6.weight"], state["features.6.bias"], 1, 1)
    np.testing.assert_allclose(fx.extract(img), y.flatten().numpy(), rtol=1e-4, atol=1e-5)


def test_loads_conv_only_file_and_hub_cache(tmp_path, monkeypatch):
    state = {k: v for k, v in _torchvision_state(3).items() if k.split(".")[1] in ("0", "3", "6")}
    hub = tmp_path / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    torch.save(state, hub / "alexnet-owt-4df8aa71.pth")
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    fx = F.VisualFeatureExtractor(backbone="auto")
    assert fx.backbone == "alexnet" and "4df8aa71" in fx.weights_source
    torch.testing.assert_close(fx.module.conv3.bias, state["features.6.bias"])


def test_missing_weights_error_says_how_to_provide_them(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="weights_path") as exc:
        F.VisualFeatureExtractor(backbone="alexnet")
    assert "hub" in str(exc.value) and "download_weights" in str(exc.value)


def test_auto_falls_back_to_efficientnet_lite0(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    fx = F.VisualFeatureExtractor(backbone="auto")
    assert fx.backbone == "efficientnet_lite0"
    f = fx.extract(np.random.default_rng(0).integers(0, 256, (60, 80, 3), dtype=np.uint8))
    assert f.shape == (fx.output_dim,) and np.isfinite(f).all()


def test_efficientnet_state_dict_loads_strictly():
    from neoslam_stream.algorithms.backbones import EfficientNetLite0
    from neoslam_stream.algorithms.weights import efficientnet_lite0_weights

    net = EfficientNetLite0()
    state = torch.load(efficientnet_lite0_weights(), map_location="cpu", weights_only=True)
    missing = net.load_state_dict(state, strict=True)
    assert not missing.missing_keys and not missing.unexpected_keys


def test_stage_strides_and_reports_backbone():
    st = a_node(backbone="random_alexnet", frame_stride=2)
    st.setup()
    msgs = [Message("image", i, i * 0.1, {"image": np.zeros((32, 32, 3), np.uint8), "encoding": "rgb8"})
            for i in range(5)]
    out = st.process_batch("image", msgs)
    assert [m.frame for _, m in out] == [0, 2, 4]
    assert st.counters["strided"] == 2
    info = st.info()
    assert info["backbone"] == "random_alexnet" and info["backbone_is_random"] is True
    assert out[0][1]["backbone"] == "random_alexnet"


def test_stage_rejects_corrupt_jpeg():
    st = a_node(backbone="random_alexnet")
    st.setup()
    bad = Message("image", 0, 0.0, {"compressed": b"\xff\xd8\xff\xe0garbage", "format": "jpeg"})
    with pytest.raises(InvalidInput, match="corrupt|truncated"):
        st.process("image", bad)


def test_failed_batch_does_not_count_strided_frames():
    # the worker retries a failed batch frame by frame; strided frames must be counted once
    st = a_node(backbone="random_alexnet", frame_stride=2)
    st.setup()
    good = [Message("image", i, 0.0, {"image": np.zeros((16, 16, 3), np.uint8)}) for i in (1, 3)]
    bad = Message("image", 2, 0.0, {"compressed": b"not an image", "format": "jpeg"})
    with pytest.raises(InvalidInput):
        st.process_batch("image", [good[0], bad, good[1]])
    assert st.counters["strided"] == 0
    for m in (good[0], good[1]):
        assert st.process("image", m) == []
    assert st.counters["strided"] == 2


@pytest.mark.parametrize("backbone", ["efficientnet_lite0", "random_alexnet"])
def test_frozen_inference_gives_the_modules_features(backbone):
    # the traced, frozen, optimised backbone computes what the module as written computes (batch
    # norm folded into the convolutions only reorders float operations), for any batch size
    imgs = [np.random.default_rng(i).integers(0, 256, (120, 208, 3), dtype=np.uint8) for i in range(3)]
    eager = F.VisualFeatureExtractor(backbone=backbone, device="cpu", inference="eager")
    frozen = F.VisualFeatureExtractor(backbone=backbone, device="cpu")
    assert eager.net is eager.module and isinstance(frozen.net, torch.jit.ScriptModule)
    a, b = eager.extract_batch(imgs), frozen.extract_batch(imgs)
    assert a.shape == b.shape == (3, frozen.output_dim)
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-5 * float(np.abs(a).max()))
    np.testing.assert_array_equal(np.stack([frozen.extract(i) for i in imgs]), b)


def test_warm_up_runs_every_batch_size_and_changes_no_feature(monkeypatch):
    # the frozen backbone is called twice on a blank batch of each size 1..max_batch (torch.jit
    # specialises to each shape on its first calls); features are the same before and after, and
    # the module as written (eager) is not called at all
    imgs = [np.random.default_rng(i).integers(0, 256, (60, 80, 3), dtype=np.uint8) for i in range(3)]
    frozen = F.VisualFeatureExtractor(backbone="random_alexnet", device="cpu")
    before = frozen.extract_batch(imgs)
    sizes = []
    net = frozen.net
    monkeypatch.setattr(frozen, "net", lambda x: (sizes.append(x.shape[0]), net(x))[1])
    frozen.warm_up(3)
    assert sizes == [1, 1, 2, 2, 3, 3]
    np.testing.assert_array_equal(frozen.extract_batch(imgs), before)
    eager = F.VisualFeatureExtractor(backbone="random_alexnet", device="cpu", inference="eager")
    called = []
    eager.module = eager.net = lambda x: called.append(x.shape[0])
    eager.warm_up(3)
    assert called == []


def test_log_standardisation_undoes_a_change_of_gain_and_gamma():
    # a gain g and a gamma y map log I to y log I + y log g: standardising each frame's log
    # intensity gives the same image for both (values chosen so that nothing clips or floors)
    rng = np.random.default_rng(3)
    img = rng.uniform(0.2, 0.8, (40, 50)).astype(np.float32)
    other = (0.7 * img) ** 1.3
    a, b = F.log_standardised(img), F.log_standardised(other)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)
    # its definition: log intensity at mean LOG_MEAN and spread LOG_SPREAD, per channel
    rgb = np.stack([img, other, 0.5 * img], axis=2)
    out = np.log(F.log_standardised(rgb).astype(np.float64))
    assert out.max() < 0  # nothing reached 1, so nothing clipped
    np.testing.assert_allclose(out.mean(axis=(0, 1)), [F.LOG_MEAN] * 3, atol=1e-5)
    np.testing.assert_allclose(out.std(axis=(0, 1)), [F.LOG_SPREAD] * 3, atol=1e-5)


def test_photometric_setting_reaches_the_backbone_input_only_when_asked():
    fx = F.VisualFeatureExtractor(backbone="random_alexnet")
    ls = F.VisualFeatureExtractor(backbone="random_alexnet", photometric="log_standardise")
    img = np.random.default_rng(4).integers(30, 220, (120, 160, 3), dtype=np.uint8)
    darker = ((img / 255.0 * 0.6) ** 1.2 * 255).round().astype(np.uint8)
    plain, std = fx.preprocess(img), ls.preprocess(img)
    as_captured = np.abs(fx.preprocess(darker) - plain).mean()  # the light shows
    # standardised: the same input up to the darker frame's 8-bit rounding and the resize, which
    # interpolates before the log is taken
    assert np.abs(ls.preprocess(darker) - std).mean() < 0.1 * as_captured
    # and the standardised grey image is what the backbone gets, after ImageNet's mean/std
    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    g = cv2.resize(grey, (341, 256), interpolation=cv2.INTER_LINEAR)[16:240, 58:282].astype(np.float32) / 255
    np.testing.assert_allclose(std[1], (F.log_standardised(g) - F.IMAGENET_MEAN[1]) / F.IMAGENET_STD[1], atol=1e-5)
    # the shipped default standardises; the paper profile keeps the paper's input bit for bit
    from neoslam_stream.config import load_config

    assert load_config("default").features.photometric == "log_standardise"
    assert load_config("paper").features.photometric == "none"
