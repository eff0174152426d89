"""SelectiveAdam: Adam on the Gaussians that the step's render saw, the others left alone.

A torch optimizer over the model's parameters (one group per parameter, rows = Gaussians, as
:func:`cdcgs.train.ops.make_optimizer` builds it), with Adam's state layout (``step``,
``exp_avg``, ``exp_avg_sq``), so the densification surgery of :mod:`cdcgs.train.ops`, checkpoints
and resume treat it as Adam, and a run may resume with the other optimizer. ``step(selected)``
updates the rows where ``selected`` [N] is True with ``cdcgs.kernels.adam.selective_adam_kernel``
and does not touch the others' parameters or moments; ``step()`` without a mask is Adam.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from .._interop import launch, warp_scope, wp_arg
from ..kernels.adam import selective_adam_kernel

__all__ = ["SelectiveAdam"]


class SelectiveAdam(torch.optim.Optimizer):
    """Adam restricted to selected rows. ``params``: tensors (or groups) whose first dimension is
    the row (the Gaussian); ``lr``, ``betas``, ``eps`` as ``torch.optim.Adam`` (no weight decay)."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        if lr < 0.0 or eps < 0.0 or not (0.0 <= betas[0] < 1.0 and 0.0 <= betas[1] < 1.0):
            raise ValueError(f"SelectiveAdam needs lr >= 0, eps >= 0 and betas in [0, 1), got {lr}, {eps}, {betas}")
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps})

    @torch.no_grad()
    def step(self, selected: torch.Tensor | None = None, closure=None):
        """One Adam step of the rows where ``selected`` [N] (bool) is True; every row without it.
        Parameters without a gradient are skipped, as Adam skips them."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        updated = [(group, p) for group in self.param_groups for p in group["params"] if p.grad is not None]
        for _, p in updated:  # every check before any update: a refused step changes nothing
            if p.dtype != torch.float32 or not p.is_contiguous():
                raise ValueError(f"SelectiveAdam updates contiguous float32 parameters, got {p.dtype} {list(p.shape)}")
            if selected is not None and (selected.shape != (p.shape[0],) or selected.dtype != torch.bool):
                raise ValueError(
                    f"selected must be a bool [{p.shape[0]}] mask (one entry per row of the parameter), "
                    f"got {selected.dtype} {list(selected.shape)}"
                )
        for group, p in updated:
            beta1, beta2 = group["betas"]
            rows = p.shape[0]
            if selected is None:
                mask = torch.ones(rows, dtype=torch.bool, device=p.device)
            else:
                mask = selected.to(p.device).contiguous()
            state = self.state[p]
            if not state:
                state["step"] = torch.zeros((), dtype=torch.float32)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
            if state["step"].device.type != "cpu":  # Adam's fused state (resume): the count on the host, once
                state["step"] = state["step"].cpu()
            state["step"] += 1
            t = float(state["step"])
            grad = p.grad.contiguous()  # held here: a launch argument does not keep its tensor alive
            width = p.numel() // rows if rows else 1
            with warp_scope(p.device):
                launch(
                    selective_adam_kernel,
                    p.numel(),
                    inputs=[
                        wp_arg(p.view(-1), wp.float32),
                        wp_arg(grad.view(-1), wp.float32),
                        wp_arg(state["exp_avg"].view(-1), wp.float32),
                        wp_arg(state["exp_avg_sq"].view(-1), wp.float32),
                        wp_arg(mask.view(torch.uint8), wp.uint8),
                        width,
                        float(group["lr"]),
                        float(beta1),
                        float(beta2),
                        1.0 - beta1,
                        1.0 - beta2,
                        float(group["eps"]),
                        1.0 - beta1**t,
                        math.sqrt(1.0 - beta2**t),
                    ],
                )
        return loss
