"""FusedAdam: Adam on every parameter in one Warp launch, optionally on selected Gaussians only.

A torch optimizer over the model's parameters (one group per parameter, rows = Gaussians, as
:func:`cdcgs.train.ops.make_optimizer` builds it), with Adam's state layout (``step``,
``exp_avg``, ``exp_avg_sq``), so the densification surgery of :mod:`cdcgs.train.ops`, checkpoints
and resume treat it as Adam, and a run may resume from a checkpoint of torch's Adam.

``step()`` is Adam: one launch of ``cdcgs.kernels.adam.fused_adam_kernel`` for all groups, where
torch's fused Adam launches once per group (six for a 3DGS model, each with its own learning
rate); a thread updates four consecutive values, with 128-bit loads and stores on CUDA.
``step(selected)`` updates only the rows where ``selected`` [N] is True and does not touch the
others' parameters or moments ("selective Adam", ``--optimizer selective``).
"""

from __future__ import annotations

import math

import torch
import warp as wp
from torch.autograd.graph import increment_version

from .._interop import halt_arg, launch, small_table, warp_scope, wp_arg
from ..kernels.adam import adam_quads, fused_adam_kernel

__all__ = ["FusedAdam", "SelectiveAdam"]


class FusedAdam(torch.optim.Optimizer):
    """Adam in one launch, optionally restricted to selected rows. ``params``: float32 tensors (or
    groups) whose first dimension is the row (the Gaussian); ``lr``, ``betas``, ``eps`` as
    ``torch.optim.Adam`` (no weight decay)."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        if lr < 0.0 or eps < 0.0 or not (0.0 <= betas[0] < 1.0 and 0.0 <= betas[1] < 1.0):
            raise ValueError(f"Adam needs lr >= 0, eps >= 0 and betas in [0, 1), got {lr}, {eps}, {betas}")
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps})

    @torch.no_grad()
    def step(
        self,
        selected: torch.Tensor | None = None,
        closure=None,
        halt: torch.Tensor | None = None,
        gradient_scale: float = 1.0,
    ):
        """One Adam step of the rows where ``selected`` [N] (bool) is True; every row without it.
        Parameters without a gradient are skipped, as Adam skips them. ``halt``: an int32 device
        flag; while its first entry is non-zero the launch changes nothing on the device (the step
        counts, kept on the host, still advance: the caller that halts restores them).
        ``gradient_scale``: the step of the gradients times this, with no pass over them (folded
        into the moments' rates, :func:`_advance`)."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        updated = [(group, p) for group in self.param_groups for p in group["params"] if p.grad is not None]
        if not updated:
            return loss
        device = updated[0][1].device
        for group, p in updated:  # every check before any update: a refused step changes nothing
            _check(group, p, self.state.get(p), device, selected)
        parameters = []  # (addresses, number of values, values per row, rates) of each parameter
        held = []  # tensors the launch reads through their addresses, alive until it is queued
        for group, p in updated:
            state = self.state[p]
            if not state:
                state["step"] = torch.zeros((), dtype=torch.float32)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
            rates = _advance(group, state, gradient_scale)
            grad = p.grad.contiguous()
            held.append(grad)
            rows = p.shape[0] if p.dim() else 1
            addresses = [x.data_ptr() for x in (p, grad, state["exp_avg"], state["exp_avg_sq"])]
            parameters.append((addresses, p.numel(), p.numel() // rows if rows else 1, rates))
        for batch in _launches(parameters):
            table, start = [], 0
            for addresses, count, width, _ in batch:
                table.append([*addresses, start, count, width])
                start += adam_quads(count)
            tables = [
                small_table(device, table, torch.int64),
                small_table(device, [e[3] for e in batch], torch.float32),
            ]
            launch_adam(tables[0], tables[1], start, selected, halt)
        for _, p in updated:  # the kernel wrote through addresses: tell torch, as an in-place op would
            increment_version(p)
        return loss

    def advance(self, params: list[torch.Tensor], gradient_scale: float = 1.0) -> list[list[float]]:
        """What ``step()`` does on the host for ``params`` (each with its Adam state), for a step
        that launches Adam itself (a captured one, :mod:`cdcgs.train.graph`): their step counts
        advanced, and their rows of ``fused_adam_kernel``'s rates table (``gradient_scale`` as
        ``step``'s)."""
        group_of = {id(p): group for group in self.param_groups for p in group["params"]}
        return [_advance(group_of[id(p)], self.state[p], gradient_scale) for p in params]


def launch_adam(
    table: torch.Tensor, rates: torch.Tensor, dim: int, selected: torch.Tensor | None, halt: torch.Tensor | None
) -> None:
    """One launch of ``fused_adam_kernel`` of ``dim`` threads (the sum of the parameters'
    ``adam_quads``, four values a thread) with its two tables (device tensors: int64 [P, 7], whose
    column 4 holds each parameter's first quad, and float32 [P, 8]), on the rows where ``selected``
    (bool [N]) is True or every row, while ``halt`` is clear."""
    device = table.device
    if selected is None:
        mask = torch.empty(0, dtype=torch.uint8, device=device)
    else:
        mask = selected.to(device).contiguous().view(torch.uint8)
    with warp_scope(device):
        launch(
            fused_adam_kernel,
            dim,
            inputs=[wp_arg(table, wp.int64), wp_arg(rates, wp.float32), wp_arg(mask, wp.uint8), halt_arg(halt, device)],
        )


def _advance(group: dict, state: dict, gradient_scale: float = 1.0) -> list[float]:
    """Advance one parameter's step count; its row of the rates table (lr, beta1, beta2, 1 - beta1,
    1 - beta2, eps and the two bias corrections of the new count, in double precision as torch
    computes them). ``gradient_scale`` s: the rates of the gradient times s, which Adam reads only
    through (1 - beta1) g and (1 - beta2) g^2: those two rates times s and s^2, so that no pass
    scales the gradients (the same step to float rounding)."""
    if state["step"].device.type != "cpu":  # torch's fused Adam keeps it on the device: once
        state["step"] = state["step"].cpu()
    state["step"] += 1
    t = float(state["step"])
    beta1, beta2 = (float(b) for b in group["betas"])
    return [
        float(group["lr"]),
        beta1,
        beta2,
        (1.0 - beta1) * gradient_scale,  # in double precision, as torch passes it
        (1.0 - beta2) * gradient_scale * gradient_scale,
        float(group["eps"]),
        1.0 - beta1**t,
        math.sqrt(1.0 - beta2**t),
    ]


# The name of ``--optimizer selective``'s optimizer before Adam and selective Adam became one class.
SelectiveAdam = FusedAdam


# A launch's indices are 32-bit: parameters are grouped into launches of fewer threads (quads of
# four values, adam_quads). The kernel indexes a parameter's values in 32 bits too.
MAX_LAUNCH_THREADS = 2**31 - 1
MAX_PARAMETER_VALUES = 2**31 - 1


def _check(group: dict, p: torch.Tensor, state: dict | None, device: torch.device, selected) -> None:
    """Refuse a parameter, its gradient, its Adam state or the mask before anything is updated
    (the kernel reads and writes them through their addresses: a wrong shape would write out of
    bounds)."""
    if p.dtype != torch.float32 or not p.is_contiguous():
        raise ValueError(f"FusedAdam updates contiguous float32 parameters, got {p.dtype} {list(p.shape)}")
    if p.device != device:
        raise ValueError(f"FusedAdam updates parameters on one device, got {p.device} and {device}")
    if p.grad.shape != p.shape:
        raise ValueError(f"a gradient of shape {list(p.grad.shape)} for a parameter of {list(p.shape)}")
    if p.numel() > MAX_PARAMETER_VALUES:
        raise ValueError(f"FusedAdam updates parameters of at most 2^31 - 1 values, got {list(p.shape)}")
    if selected is not None and p.dim() == 0:
        raise ValueError("selected picks rows, and a 0-d parameter has none")
    if selected is not None and (selected.shape != (p.shape[0],) or selected.dtype != torch.bool):
        raise ValueError(
            f"selected must be a bool [{p.shape[0]}] mask (one entry per row of the parameter), "
            f"got {selected.dtype} {list(selected.shape)}"
        )
    lr, eps, betas = group.get("lr"), group.get("eps"), group.get("betas")
    if not _number(lr) or float(lr) < 0.0:
        raise ValueError(f"FusedAdam needs a learning rate >= 0 for every group, got {lr!r}")
    if not _number(eps) or float(eps) < 0.0:
        raise ValueError(f"FusedAdam needs eps >= 0 for every group, got {eps!r}")
    if not (
        isinstance(betas, (tuple, list))
        and len(betas) == 2
        and all(_number(b) and 0.0 <= float(b) < 1.0 for b in betas)
    ):
        raise ValueError(f"FusedAdam needs two betas in [0, 1) for every group, got {betas!r}")
    for key in ("amsgrad", "weight_decay", "maximize"):
        if group.get(key):  # a state loaded from torch's Adam carries its options
            raise ValueError(f"FusedAdam is Adam without {key}, but a parameter group sets {key}={group[key]!r}")
    if state:
        if "step" not in state:
            raise ValueError(f"the Adam state of a {list(p.shape)} parameter has no step count")
        for key in ("exp_avg", "exp_avg_sq"):
            moment = state.get(key)
            if not (
                isinstance(moment, torch.Tensor)
                and moment.shape == p.shape
                and moment.dtype == torch.float32
                and moment.device == p.device
                and moment.is_contiguous()
            ):
                if isinstance(moment, torch.Tensor):
                    layout = "" if moment.is_contiguous() else ", not contiguous"
                    got = f"{moment.dtype} {list(moment.shape)} on {moment.device}{layout}"
                else:
                    got = "nothing" if moment is None else type(moment).__name__
                raise ValueError(
                    f"the Adam state {key!r} of a {list(p.shape)} parameter must be a contiguous float32 tensor "
                    f"of its shape on {p.device}, got {got}"
                )


def _number(value) -> bool:
    """A float, an int or a one-value tensor (torch allows a tensor learning rate), not a bool."""
    if isinstance(value, torch.Tensor):
        return value.numel() == 1
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _launches(parameters: list) -> list[list]:
    """The parameters in order, grouped into launches of at most MAX_LAUNCH_THREADS threads (one
    launch unless the model is very large)."""
    batches, total = [[]], 0
    for entry in parameters:
        threads = adam_quads(entry[1])
        if total + threads > MAX_LAUNCH_THREADS:
            batches.append([])
            total = 0
        batches[-1].append(entry)
        total += threads
    return [batch for batch in batches if batch]
