"""Every change to the set of Gaussians, as free functions that keep Adam's moments in step with
the parameters: append, remove (prune), clone, split, reset opacity, relocate; and the optimizer
they act on.

Each function takes the model and its optimizer (one named Adam group per parameter, as
:func:`make_optimizer` builds it) and replaces the parameter tensors and their moments together.
Strategies call these; none of them keeps state of its own.
"""

from __future__ import annotations

import math

import torch

from ..geometry import quat_to_rotation
from .config import OPTIMIZERS, LearningRates
from .model import PARAM_NAMES, GaussianModel
from .optim import FusedAdam

__all__ = [
    "append",
    "clone",
    "load_optimizer_state",
    "make_optimizer",
    "morton_order",
    "relocate",
    "remove",
    "reorder",
    "reset_opacity",
    "set_hyperparameters",
    "split",
]


def make_optimizer(
    model: GaussianModel,
    lrs: LearningRates,
    extent: float,
    kind: str = "adam",
    batch_rule: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> torch.optim.Optimizer:
    """One Adam parameter group per parameter, named, with the 3DGS rates (eps 1e-15 as 3DGS).

    "adam" and "selective": :class:`cdcgs.train.optim.FusedAdam` (all groups in one Warp launch);
    "adam" steps every Gaussian, "selective" tells the trainer to pass ``step`` the mask of the
    Gaussians the view sees. "torch-adam": torch's Adam (fused on CUDA, one launch per group), the
    reference that FusedAdam replaced. ``batch_rule``: (learning-rate factor, eps factor, beta
    power) of a batch of views per step (:func:`cdcgs.train.config.batch_rule`).
    """
    if kind not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {', '.join(OPTIMIZERS)}, got {kind!r}")
    groups = [{"params": [model.params[name]], "name": name} for name in PARAM_NAMES]
    if kind == "torch-adam":
        # Fused on CUDA (torch before 2.4 has no fused Adam on the CPU, where its loop runs instead).
        cuda = model.params[PARAM_NAMES[0]].device.type == "cuda"
        optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True if cuda else None)
    else:
        optimizer = FusedAdam(groups, lr=0.0, eps=1e-15)
    set_hyperparameters(optimizer, lrs, extent, batch_rule)
    return optimizer


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: dict) -> None:
    """Load a checkpoint's optimizer state into ``optimizer``, whichever Adam saved it: the groups
    keep this optimizer's own implementation (torch's ``fused``, ``foreach`` and ``capturable``,
    which torch would otherwise take from the saved groups or reset), options the saver's groups
    lack (torch's ``weight_decay`` in a FusedAdam state) get this optimizer's defaults, and a fused or capturable
    torch Adam gets its step counts on the parameters' device, where it reads them."""
    keys = ("fused", "foreach", "capturable")
    flags = [{k: g[k] for k in keys if k in g} for g in optimizer.param_groups]
    optimizer.load_state_dict(state)
    for group, own in zip(optimizer.param_groups, flags):
        for key, value in optimizer.defaults.items():  # options the saver's groups did not have
            group.setdefault(key, value)
        for key in keys:
            if key in own:
                group[key] = own[key]
            else:  # a flag of the optimizer that saved the state, not of this one
                group.pop(key, None)
        if group.get("fused") or group.get("capturable"):
            for p in group["params"]:
                moments = optimizer.state.get(p)
                if moments and torch.is_tensor(moments.get("step")):
                    moments["step"] = moments["step"].to(device=p.device, dtype=torch.float32)


def set_hyperparameters(
    optimizer: torch.optim.Optimizer,
    lrs: LearningRates,
    extent: float,
    batch_rule: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> None:
    """Set every group's learning rate, eps and betas: the rates of ``lrs`` (positions x
    ``extent``) times the batch rule's factor, eps 1e-15 times its eps factor, Adam's betas
    (0.9, 0.999) to its power. A resumed run calls it after loading the optimizer's state, so the
    command's options hold, not the checkpoint's."""
    lr_scale, eps_scale, beta_power = batch_rule
    rates = {
        "means": lrs.means_init * extent,
        "log_scales": lrs.log_scales,
        "quats": lrs.quats,
        "opacity_logits": lrs.opacity_logits,
        "sh_dc": lrs.sh_dc,
        "sh_rest": lrs.sh_rest,
    }
    for group in optimizer.param_groups:
        rate = rates[group["name"]]
        group["lr"] = None if rate is None else rate * lr_scale  # None: left for the caller to set
        group["eps"] = 1e-15 * eps_scale
        group["betas"] = (0.9**beta_power, 0.999**beta_power)


def _update(model: GaussianModel, optimizer: torch.optim.Optimizer, make_param, make_moment) -> None:
    """Replace every parameter p by make_param(name, p) and each Adam moment m by
    make_moment(name, m)."""
    for group in optimizer.param_groups:
        name = group["name"]
        old = group["params"][0]
        new = torch.nn.Parameter(make_param(name, old.detach()).contiguous())
        state = optimizer.state.pop(old, None)
        if state is not None:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key] = make_moment(name, state[key]).contiguous()
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
        lambda name, m: torch.cat([m, m.new_zeros(count, *m.shape[1:])]),
    )


def remove(model: GaussianModel, optimizer: torch.optim.Optimizer, mask: torch.Tensor) -> None:
    """Remove (prune) the Gaussians where ``mask`` [N] is True, with their Adam moments."""
    keep = ~mask
    _update(model, optimizer, lambda name, p: p[keep], lambda name, m: m[keep])


def reorder(model: GaussianModel, optimizer: torch.optim.Optimizer, order: torch.Tensor) -> None:
    """Put the Gaussians in ``order`` (a permutation of 0..N-1: the new row i is the old row
    ``order[i]``), with their Adam moments."""
    _update(model, optimizer, lambda name, p: p[order], lambda name, m: m[order])


MORTON_BITS = 21  # a cell's coordinate on each axis: 3 x 21 bits fill an int64


def _spread_bits(x: torch.Tensor) -> torch.Tensor:
    """The MORTON_BITS low bits of ``x`` (int64), two zero bits between each."""
    x = x & ((1 << MORTON_BITS) - 1)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        x = (x | (x << shift)) & mask
    return x


def morton_order(means: torch.Tensor) -> torch.Tensor:
    """The permutation that sorts ``means`` [N, 3] by the Morton (Z-order) code of their cell in a
    grid of 2^21 cells a side over their bounding box, ties (a clone and its parent share a cell) in
    their order: Gaussians near in space end up near in memory. A non-finite coordinate counts as 0."""
    means = torch.nan_to_num(means.detach().float(), nan=0.0, posinf=0.0, neginf=0.0)
    if means.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=means.device)
    low, high = means.min(0).values, means.max(0).values
    top = (1 << MORTON_BITS) - 1
    cells = ((means - low) / (high - low).clamp_min(1e-30) * top).long().clamp(0, top)
    codes = _spread_bits(cells[:, 0]) | (_spread_bits(cells[:, 1]) << 1) | (_spread_bits(cells[:, 2]) << 2)
    return torch.sort(codes, stable=True).indices


def clone(model: GaussianModel, optimizer: torch.optim.Optimizer, mask: torch.Tensor) -> None:
    """Append a copy of each selected Gaussian (3DGS's clone of small Gaussians); copies start
    with zero moments."""
    append(model, optimizer, {name: p.detach()[mask] for name, p in model.params.items()})


def split(
    model: GaussianModel,
    optimizer: torch.optim.Optimizer,
    mask: torch.Tensor,
    *,
    count: int = 2,
    scale_divisor: float = 1.6,
    generator: torch.Generator | None = None,
) -> None:
    """Replace each selected Gaussian by ``count`` sampled from it, with scales / ``scale_divisor``.

    New means are drawn from the parent's Gaussian (mean + R diag(s) z, z ~ N(0, I), with
    ``generator``); everything else is copied. The parents are removed and the children appended
    (order: the unselected Gaussians, then the children).
    """
    p = {name: t.detach()[mask] for name, t in model.params.items()}
    n = p["means"].shape[0]
    scales = p["log_scales"].exp().repeat(count, 1)
    rotation = quat_to_rotation(p["quats"]).repeat(count, 1, 1)
    noise = torch.randn(n * count, 3, device=scales.device, generator=generator)
    offsets = (rotation @ (scales * noise)[..., None])[..., 0]
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


def relocate(
    model: GaussianModel,
    optimizer: torch.optim.Optimizer,
    targets: torch.Tensor,
    sources: torch.Tensor,
    new_values: dict[str, torch.Tensor] | None = None,
    *,
    restart_targets: bool = True,
) -> None:
    """Move Gaussians in place: ``targets`` [M] (indices, e.g. dead Gaussians) take the parameters
    of ``sources`` [M] (indices), overridden per parameter by ``new_values`` (name -> [M, ...]
    pre-activation values, e.g. the opacity and scales that 3DGS-MCMC recomputes for the sources
    and their copies, which are then also written to ``sources``). The moments of every touched
    Gaussian restart at zero, or with ``restart_targets`` False only the sources' (the targets keep
    the moments of the Gaussians they replace, as the 3DGS-MCMC code and gsplat leave them); the
    count N does not change.
    """
    targets, sources = targets.long(), sources.long()
    if targets.shape != sources.shape or targets.dim() != 1:
        raise ValueError(
            f"targets and sources must be index vectors of one length, got {list(targets.shape)} and {list(sources.shape)}"
        )
    new_values = new_values or {}
    unknown = sorted(set(new_values) - set(PARAM_NAMES))
    if unknown:
        raise ValueError(f"relocate: no parameters {unknown}; the model has {list(PARAM_NAMES)}")
    touched = torch.cat([targets, sources]) if restart_targets else sources

    def move(name, p):
        p = p.clone()
        values = new_values.get(name)
        if values is None:
            p[targets] = p[sources]
        else:
            values = values.to(p.dtype)
            p[sources] = values
            p[targets] = values
        return p

    def restart(name, m):
        m = m.clone()
        m[touched] = 0
        return m

    _update(model, optimizer, move, restart)
