"""Gaussian parameters as torch tensors, their per-parameter Adam, and the tensor surgery that
densification strategies share (duplicate, split, remove, reset opacity), keeping Adam's state
in step with the parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..io.ply import GaussianPly
from ..neighbors import initial_scales

SH_C0 = 0.28209479177387814
PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


@dataclass(kw_only=True)
class LearningRates:
    """Adam learning rates per parameter (3DGS defaults). Position rates are x scene extent."""

    means_init: float = 1.6e-4
    means_final: float = 1.6e-6
    log_scales: float = 5e-3
    quats: float = 1e-3
    opacity_logits: float = 5e-2
    sh_dc: float = 2.5e-3
    sh_rest: float = 2.5e-3 / 20


def position_lr(step: int, total_steps: int, lrs: LearningRates, extent: float) -> float:
    """Exponential decay from means_init to means_final (x extent) over the run (3DGS)."""
    t = min(max(step / max(total_steps, 1), 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(lrs.means_init) + t * math.log(lrs.means_final))


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
    def from_points(cls, points: torch.Tensor, colors: torch.Tensor, *, max_sh_degree: int = 3, init_opacity: float = 0.1, scale_rule: str = "3dgs", device="cpu") -> GaussianModel:
        """Gaussians at the points [P, 3] with their uint8 colours [P, 3]: scales from the 3 nearest
        neighbours (``scale_rule`` "3dgs" or "cdc"), identity rotations, opacity 0.1, degree-0 SH."""
        points = points.to(device, torch.float32).contiguous()
        n = points.shape[0]
        if n < 4:
            raise ValueError(f"need at least 4 initial points to measure neighbour distances, got {n}")
        scales = initial_scales(points, scale_rule)
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
        """Keyword arguments of :func:`cdcgs.rasterize` for the current state (differentiable)."""
        k = (self.sh_degree + 1) ** 2
        return dict(
            means=self.params["means"],
            quats=self.params["quats"],
            scales=self.scales(),
            opacities=self.opacities(),
            sh=self.sh()[:, :k],
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

    def state_dict(self) -> dict:
        return {"params": {k: v.detach() for k, v in self.params.items()}, "max_sh_degree": self.max_sh_degree, "sh_degree": self.sh_degree}

    @classmethod
    def from_state_dict(cls, state: dict, device="cpu") -> GaussianModel:
        params = {k: v.to(device) for k, v in state["params"].items()}
        return cls(params, max_sh_degree=state["max_sh_degree"], sh_degree=state["sh_degree"])


def make_optimizer(model: GaussianModel, lrs: LearningRates, extent: float) -> torch.optim.Adam:
    """One Adam parameter group per parameter, named, with the 3DGS rates (eps 1e-15 as 3DGS).

    On CUDA the fused implementation (one kernel per group instead of a chain of foreach kernels).
    """
    rates = {
        "means": lrs.means_init * extent,
        "log_scales": lrs.log_scales,
        "quats": lrs.quats,
        "opacity_logits": lrs.opacity_logits,
        "sh_dc": lrs.sh_dc,
        "sh_rest": lrs.sh_rest,
    }
    groups = [{"params": [model.params[name]], "lr": rates[name], "name": name} for name in PARAM_NAMES]
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=model.device.type == "cuda")


# ------------------------------------------------------------------------------------------
# Surgery shared by every strategy: parameters and Adam moments change together.


def _update(model: GaussianModel, optimizer: torch.optim.Optimizer, make_param, make_moment) -> None:
    """Replace every parameter p by make_param(name, p) and each Adam moment m by make_moment(m)."""
    for group in optimizer.param_groups:
        name = group["name"]
        old = group["params"][0]
        new = torch.nn.Parameter(make_param(name, old.detach()).contiguous())
        state = optimizer.state.pop(old, None)
        if state is not None:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key] = make_moment(state[key]).contiguous()
            optimizer.state[new] = state
        group["params"][0] = new
        model.params[name] = new


def append(model: GaussianModel, optimizer: torch.optim.Optimizer, new: dict[str, torch.Tensor]) -> None:
    """Add Gaussians (pre-activation values per parameter); their Adam moments start at zero."""
    count = new["means"].shape[0]
    _update(
        model,
        optimizer,
        lambda name, p: torch.cat([p, new[name].to(p.dtype)]),
        lambda m: torch.cat([m, m.new_zeros(count, *m.shape[1:])]),
    )


def remove(model: GaussianModel, optimizer: torch.optim.Optimizer, mask: torch.Tensor) -> None:
    """Remove the Gaussians where ``mask`` [N] is True, with their Adam moments."""
    keep = ~mask
    _update(model, optimizer, lambda name, p: p[keep], lambda m: m[keep])


def duplicate(model: GaussianModel, optimizer: torch.optim.Optimizer, mask: torch.Tensor) -> None:
    """Clone the selected Gaussians in place (3DGS's clone of small Gaussians)."""
    append(model, optimizer, {name: p.detach()[mask] for name, p in model.params.items()})


def split(model: GaussianModel, optimizer: torch.optim.Optimizer, mask: torch.Tensor, *, count: int = 2, scale_divisor: float = 1.6, generator: torch.Generator | None = None) -> None:
    """Replace each selected Gaussian by ``count`` sampled from it, with scales / ``scale_divisor``.

    New means are drawn from the parent's Gaussian (mean + R diag(s) z, z ~ N(0, I)), so they lie
    inside its 3-sigma ellipsoid with high probability; everything else is copied.
    """
    p = {name: t.detach()[mask] for name, t in model.params.items()}
    n = p["means"].shape[0]
    scales = p["log_scales"].exp().repeat(count, 1)
    q = torch.nn.functional.normalize(p["quats"], dim=-1).repeat(count, 1)
    w, x, y, z = q.unbind(-1)
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(-1, 3, 3)  # fmt: skip
    noise = torch.randn(n * count, 3, device=scales.device, generator=generator)
    offsets = (rot @ (scales * noise)[..., None])[..., 0]
    new = {name: t.repeat(count, *([1] * (t.dim() - 1))) for name, t in p.items()}
    new["means"] = new["means"] + offsets
    new["log_scales"] = (scales / scale_divisor).log()
    remove(model, optimizer, mask)
    append(model, optimizer, new)


def reset_opacity(model: GaussianModel, optimizer: torch.optim.Optimizer, value: float = 0.01) -> None:
    """Clamp every opacity to at most ``value`` and zero the opacity's Adam moments (3DGS)."""
    cap = math.log(value / (1 - value))
    for group in optimizer.param_groups:
        if group["name"] != "opacity_logits":
            continue
        old = group["params"][0]
        new = torch.nn.Parameter(old.detach().clamp_max(cap))
        state = optimizer.state.pop(old, None)
        if state is not None:
            state["exp_avg"] = torch.zeros_like(state["exp_avg"])
            state["exp_avg_sq"] = torch.zeros_like(state["exp_avg_sq"])
            optimizer.state[new] = state
        group["params"][0] = new
        model.params["opacity_logits"] = new
