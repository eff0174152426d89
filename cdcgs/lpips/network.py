"""LPIPS v0.1 (Zhang et al., CVPR 2018) as a small torch module that needs no torchvision.

The score of two images is, as the reference ``lpips`` package computes it: both images in
[-1, 1] pass the scaling layer ((x - shift) / scale), then the feature stack of AlexNet or VGG16;
at each of five taps the channels are scaled to unit length, the squared difference of the two
images' features is weighted per channel by a linear head (1x1 convolution, no bias), averaged
over the tap's pixels, and the five averages are summed.
"""

from __future__ import annotations

import contextlib

import torch
from torch import nn

__all__ = ["ALEX_LAYERS", "LPIPS", "NETS", "SCALE", "SHIFT", "VGG_LAYERS", "float32_convolutions"]

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10  # the reference's in normalize_tensor

# (out channels, kernel, stride, padding, max-pool (kernel, stride) before the conv or None,
# a tap after its ReLU), in torchvision's order of the feature stack.
ALEX_LAYERS = (
    (64, 11, 4, 2, None, True),
    (192, 5, 1, 2, (3, 2), True),
    (384, 3, 1, 1, (3, 2), True),
    (256, 3, 1, 1, None, True),
    (256, 3, 1, 1, None, True),
)
_VGG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_VGG_TAPS = (1, 4, 8, 12, 16)  # indices in _VGG of relu1_2, relu2_2, relu3_3, relu4_3, relu5_3


def _vgg_layers() -> tuple:
    layers, pool = [], None
    for index, entry in enumerate(_VGG):
        if entry == "M":
            pool = (2, 2)
            continue
        layers.append((entry, 3, 1, 1, pool, index in _VGG_TAPS))
        pool = None
    return tuple(layers)


VGG_LAYERS = _vgg_layers()
NETS = {"vgg": VGG_LAYERS, "alex": ALEX_LAYERS}


@contextlib.contextmanager
def float32_convolutions(cudnn: bool = False):
    """Convolutions and matrix products in full float32, not TF32 (which cuDNN uses by default on
    Ampere and newer GPUs, and which moves LPIPS scores by up to 1e-4): the scores are then the
    same on every GPU and on the CPU, to about 1e-6.

    On a GPU the convolutions run on torch's own kernels, not cuDNN's (``cudnn=False``, the
    default): one im2col buffer per convolution, looped over the images, and a cuBLAS GEMM, so the
    memory is bounded by the layer sizes, not by what cuDNN asks for. The largest im2col buffer
    of LPIPS-VGG at 800 x 533 pixels is 64 x 9 rows of 800 x 533 floats, 0.98 GB. With cuDNN,
    PyTorch takes the first engine of cuDNN's heuristics whose workspace it can allocate, which on
    a large GPU may be tens of GB (pytorch/pytorch#49207): the evaluations of the bonsai trainings
    (37 views of 800 x 533, LPIPS in batches of two images, cuDNN's deterministic algorithms and
    benchmark mode off) peaked at 37.5 GB on an H100 against 1-2.8 GB for the training, whatever
    the number of Gaussians. The memory and the time of the change are not yet measured on a GPU
    (``benchmarks/eval_memory.py`` measures both). ``cudnn=True`` keeps cuDNN, restricted to its
    deterministic algorithms with benchmark mode off: the settings before the change, for
    comparison. On the CPU both are the same."""
    backends = torch.backends
    saved = (
        backends.cudnn.enabled,
        backends.cudnn.allow_tf32,
        backends.cuda.matmul.allow_tf32,
        backends.cudnn.deterministic,
        backends.cudnn.benchmark,
    )
    backends.cudnn.enabled = cudnn
    backends.cudnn.allow_tf32 = backends.cuda.matmul.allow_tf32 = False
    backends.cudnn.deterministic, backends.cudnn.benchmark = True, False
    try:
        yield
    finally:
        (
            backends.cudnn.enabled,
            backends.cudnn.allow_tf32,
            backends.cuda.matmul.allow_tf32,
            backends.cudnn.deterministic,
            backends.cudnn.benchmark,
        ) = saved


class LPIPS(nn.Module):
    """LPIPS distance of image pairs, with the ``net`` ("vgg" or "alex") backbone.

    Parameters (``state_dict`` keys): ``convs.{i}.weight`` [out, in, k, k] and ``convs.{i}.bias``
    [out] of the backbone's convolutions in order, ``heads.{t}`` [channels] of the five linear
    heads. Load them with :func:`cdcgs.lpips.load_lpips` (checked weights), or any state dict of
    this layout.

    ``forward(a, b)``: images [B, 3, H, W] in [0, 1] (mapped to [-1, 1] inside, as the reference
    does with ``normalize=True``) -> [B] distances. Both images of a pair must have one size, at
    least 31 x 31 pixels for "alex" and 16 x 16 for "vgg" so that every tap has a pixel.

    ``cudnn``: run the convolutions on cuDNN instead of torch's own kernels (see
    :func:`float32_convolutions`; off by default, as the evaluation runs them); an attribute that
    may also be set after loading.
    """

    def __init__(self, net: str = "vgg", *, cudnn: bool = False):
        super().__init__()
        self.cudnn = cudnn
        if net not in NETS:
            raise ValueError(f"LPIPS net must be one of {', '.join(NETS)}, got {net!r}")
        self.net = net
        self.layers = NETS[net]
        channels, convs, heads = 3, [], []
        for out, kernel, stride, padding, _, tap in self.layers:
            convs.append(nn.Conv2d(channels, out, kernel, stride=stride, padding=padding))
            if tap:
                heads.append(nn.Parameter(torch.zeros(out)))
            channels = out
        self.convs = nn.ModuleList(convs)
        self.heads = nn.ParameterList(heads)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    @property
    def min_size(self) -> int:
        return 31 if self.net == "alex" else 16

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five taps (after the scaling layer) of images in [-1, 1], [B, 3, H, W]."""
        x = (x - self.shift) / self.scale
        taps = []
        for conv, (_, _, _, _, pool, tap) in zip(self.convs, self.layers):
            if pool is not None:
                x = nn.functional.max_pool2d(x, pool[0], stride=pool[1])
            x = torch.relu(conv(x))
            if tap:
                taps.append(x)
        return taps

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        self._check(a, b)
        with float32_convolutions(cudnn=self.cudnn):
            return self._distance(a, b)

    def _distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        features = self.features(torch.cat([a, b]) * 2.0 - 1.0)
        total = 0.0
        for feature, head in zip(features, self.heads):
            fa, fb = feature.chunk(2)
            fa = fa / (fa.square().sum(1, keepdim=True).sqrt() + EPS)
            fb = fb / (fb.square().sum(1, keepdim=True).sqrt() + EPS)
            total = total + torch.einsum("bchw,c->bhw", (fa - fb).square(), head).mean(dim=(1, 2))
        return total

    def _check(self, a: torch.Tensor, b: torch.Tensor) -> None:
        for name, x in (("first image", a), ("second image", b)):
            if not isinstance(x, torch.Tensor) or x.dim() != 4 or x.shape[1] != 3:
                shape = list(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
                raise ValueError(f"LPIPS: the {name} must be a [B, 3, H, W] tensor, got {shape}")
            if min(x.shape[2:]) < self.min_size:
                raise ValueError(
                    f"LPIPS-{self.net}: images must be at least {self.min_size} x {self.min_size} pixels, got {list(x.shape[2:])}"
                )
            if not torch.isfinite(x).all():
                raise ValueError(f"LPIPS: the {name} has NaN or infinite values")
        if a.shape != b.shape:
            raise ValueError(f"LPIPS: the two images differ in shape: {list(a.shape)} and {list(b.shape)}")
