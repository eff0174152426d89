"""The trainable Gaussians: a plain container of pre-activation parameters, their activations,
and conversions to and from PLY and checkpoints. Surgery on them (and on Adam's state) lives in
:mod:`cdcgs.train.ops`."""

from __future__ import annotations

import math

import torch

from ..io.ply import GaussianPly
from ..kernels._constants import SH_C0
from ..neighbors import initial_scales

__all__ = ["PARAM_NAMES", "GaussianModel"]

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


class GaussianModel:
    """The trainable Gaussians: pre-activation parameters as leaf tensors in ``params``.

    means [N, 3]; log_scales [N, 3] (scale = exp); quats [N, 4] (w, x, y, z, normalised when
    rendering); opacity_logits [N] (opacity = sigmoid); sh_dc [N, 1, 3]; sh_rest [N, K-1, 3].
    """

    def __init__(self, params: dict[str, torch.Tensor], max_sh_degree: int = 3, sh_degree: int = 0):
        self.params = {name: torch.nn.Parameter(params[name].detach().contiguous()) for name in PARAM_NAMES}
        self.max_sh_degree = max_sh_degree
        self.sh_degree = sh_degree

    @classmethod
    def from_points(
        cls,
        points: torch.Tensor,
        colors: torch.Tensor,
        *,
        max_sh_degree: int = 3,
        init_opacity: float = 0.1,
        scale_rule: str = "3dgs",
        scale_factor: float = 1.0,
        device="cpu",
    ) -> GaussianModel:
        """Gaussians at the points [P, 3] with their uint8 colours [P, 3]: scales from the 3 nearest
        neighbours (``scale_rule`` "3dgs" or "cdc") times ``scale_factor``, identity rotations,
        opacity ``init_opacity``, degree-0 SH."""
        points = points.to(device, torch.float32).contiguous()
        n = points.shape[0]
        if n < 4:
            raise ValueError(f"need at least 4 initial points to measure neighbour distances, got {n}")
        scales = initial_scales(points, scale_rule) * scale_factor
        quats = torch.zeros(n, 4, device=device)
        quats[:, 0] = 1.0
        rgb = colors.to(device, torch.float32) / 255.0
        k = (max_sh_degree + 1) ** 2
        params = {
            "means": points,
            "log_scales": scales.log()[:, None].repeat(1, 3),
            "quats": quats,
            "opacity_logits": torch.full((n,), math.log(init_opacity / (1 - init_opacity)), device=device),
            "sh_dc": ((rgb - 0.5) / SH_C0)[:, None, :],
            "sh_rest": torch.zeros(n, k - 1, 3, device=device),
        }
        return cls(params, max_sh_degree=max_sh_degree)

    @property
    def num(self) -> int:
        return self.params["means"].shape[0]

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    def scales(self) -> torch.Tensor:
        return self.params["log_scales"].exp()

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacity_logits"])

    def sh(self) -> torch.Tensor:
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)

    def render_args(self) -> dict:
        """Keyword arguments of :func:`cdcgs.rasterize` for the current state (differentiable).

        The two coefficient tensors go to the render as they are (``sh`` and ``sh_rest``), which
        evaluates those of ``sh_degree``: concatenating them, or slicing to the degree, would copy
        every coefficient each iteration (and their gradients back)."""
        return dict(
            means=self.params["means"],
            quats=self.params["quats"],
            scales=self.scales(),
            opacities=self.opacities(),
            sh=self.params["sh_dc"],
            sh_rest=self.params["sh_rest"],
            sh_degree=self.sh_degree,
        )

    def to_ply(self) -> GaussianPly:
        return GaussianPly(
            means=self.params["means"].detach(),
            log_scales=self.params["log_scales"].detach(),
            quats=self.params["quats"].detach(),
            opacity_logits=self.params["opacity_logits"].detach(),
            sh=self.sh().detach(),
        )

    @classmethod
    def from_ply(cls, ply: GaussianPly, device="cpu") -> GaussianModel:
        sh = ply.sh.to(device)
        params = {
            "means": ply.means.to(device),
            "log_scales": ply.log_scales.to(device),
            "quats": ply.quats.to(device),
            "opacity_logits": ply.opacity_logits.to(device),
            "sh_dc": sh[:, :1],
            "sh_rest": sh[:, 1:],
        }
        degree = ply.sh_degree
        return cls(params, max_sh_degree=degree, sh_degree=degree)

    def nonfinite(self) -> list[str]:
        """Names of the parameters that hold NaN or infinite values (empty when all are finite)."""
        return [name for name, value in self.params.items() if not torch.isfinite(value).all()]

    def state_dict(self) -> dict:
        return {
            "params": {k: v.detach() for k, v in self.params.items()},
            "max_sh_degree": self.max_sh_degree,
            "sh_degree": self.sh_degree,
        }

    @classmethod
    def from_state_dict(cls, state: dict, device="cpu") -> GaussianModel:
        params = {k: v.to(device) for k, v in state["params"].items()}
        return cls(params, max_sh_degree=state["max_sh_degree"], sh_degree=state["sh_degree"])
