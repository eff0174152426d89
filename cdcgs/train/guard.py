"""The numeric guard of a training: non-finite or exploding numbers stop the run, named.

Every iteration, :meth:`NumericGuard.record` adds to a few device tensors, without reading
anything back to the host: the first iteration whose loss was NaN or infinite, the first whose
gradients were (their total norm is then not finite), and the first at which the running mean of
the loss exploded (rose above ``EXPLODE_FACTOR`` times the loss of the run's first iteration, and
above ``EXPLODE_FLOOR``: a photometric loss of images in [0, 1] stays below 1.2, so only renders
far outside that range reach it). The trainer reads them, one host synchronisation, with
:meth:`NumericGuard.check` where it reads numbers anyway: at log steps, before a strategy changes
the Gaussians, before an evaluation and before every checkpoint or PLY it writes; the last also
checks that every parameter is finite. A tripped check raises :class:`TrainingDiverged`, which
names what went wrong, when, and the learning rates in force.
"""

from __future__ import annotations

import torch

__all__ = ["EXPLODE_FACTOR", "EXPLODE_FLOOR", "NumericGuard", "TrainingDiverged"]

EXPLODE_FACTOR = 4.0
EXPLODE_FLOOR = 1.5
SMOOTHING = 0.9  # running means: m <- 0.9 m + 0.1 x
_NEVER = 2**62  # "no such iteration" in the first-iteration records
_CAUSES = ("the loss became NaN or infinite", "the gradients became NaN or infinite", "the loss exploded")


class TrainingDiverged(RuntimeError):
    """The run's numbers went wrong; nothing of the bad state was written (the message says
    which checkpoint holds the last good one)."""


class NumericGuard:
    """Device-side records of a run's numbers, read only by :meth:`check` (see the module)."""

    def __init__(self, device: torch.device, state: dict | None = None):
        self.device = torch.device(device)
        self.first_bad = torch.full((len(_CAUSES),), _NEVER, dtype=torch.int64, device=self.device)
        self.loss_mean: torch.Tensor | None = None  # running means, also what the console shows
        self.psnr_mean: torch.Tensor | None = None
        self.reference: torch.Tensor | None = None  # the loss of the run's first iteration
        if state:
            self.load_state_dict(state)

    def record(self, step: int, loss: torch.Tensor, psnr: torch.Tensor, grads: list[torch.Tensor]) -> None:
        """Add iteration ``step``'s loss, PSNR and gradients; no host synchronisation."""
        loss, psnr = loss.detach().float(), psnr.detach().float()
        if grads:
            norm = torch.nn.utils.get_total_norm(grads).to(self.device)
        else:
            norm = torch.zeros((), device=self.device)
        if self.loss_mean is None:
            self.loss_mean, self.psnr_mean = loss.clone(), psnr.clone()
        else:
            self.loss_mean.mul_(SMOOTHING).add_(loss, alpha=1 - SMOOTHING)
            self.psnr_mean.mul_(SMOOTHING).add_(psnr, alpha=1 - SMOOTHING)
        if self.reference is None:
            self.reference = loss.clone()
        limit = (self.reference * EXPLODE_FACTOR).clamp_min(EXPLODE_FLOOR)
        bad = torch.stack([~torch.isfinite(loss), ~torch.isfinite(norm), self.loss_mean > limit])
        torch.minimum(self.first_bad, torch.where(bad, step, _NEVER), out=self.first_bad)

    def means(self) -> tuple[float, float]:
        """The running means of the loss and the PSNR (a host synchronisation)."""
        if self.loss_mean is None:
            return float("nan"), float("nan")
        loss, psnr = torch.stack([self.loss_mean, self.psnr_mean]).tolist()
        return loss, psnr

    def check(self, step: int, optimizer: torch.optim.Optimizer, params: dict | None = None, last_good: str = ""):
        """Raise :class:`TrainingDiverged` when a record has tripped or (with ``params``, a dict of
        tensors) a parameter is not finite. One host synchronisation. ``last_good`` ends the
        message: where the last good state is."""
        values = [self.first_bad]
        names = []
        if params:
            names = list(params)
            values.append(torch.stack([~torch.isfinite(p.detach()).all() for p in params.values()]).to(self.device))
        read = torch.cat(values).tolist()
        first = read[: len(_CAUSES)]
        nonfinite = [name for name, bad in zip(names, read[len(_CAUSES) :]) if bad]
        causes = [f"{cause} at iteration {at}" for cause, at in zip(_CAUSES, first) if at != _NEVER]
        if nonfinite:
            causes.append(f"the parameters {', '.join(nonfinite)} hold NaN or infinite values")
        if causes:
            raise self.diverged(step, optimizer, "; ".join(causes), last_good)

    def diverged(self, step: int, optimizer, cause: str, last_good: str) -> TrainingDiverged:
        """The error of a run stopped at ``step`` for ``cause``, naming the learning rates."""
        detail = ""
        if "exploded" in cause and self.loss_mean is not None:
            mean, reference = torch.stack([self.loss_mean, self.reference]).tolist()
            detail = f" (running mean {mean:.4g} against {reference:.4g} at the first iteration)"
        rates = ", ".join(f"{group.get('name', i)} {group['lr']:.3g}" for i, group in enumerate(optimizer.param_groups))
        return TrainingDiverged(
            f"training stopped at iteration {step}: {cause}{detail}. The learning rates in force: {rates}; "
            f"a rate too high for this scene is the usual cause (lower it with --lr-*). {last_good}"
        )

    def state_dict(self) -> dict:
        """What a checkpoint keeps: the running means and the reference loss (CPU tensors)."""
        return {
            name: None if value is None else value.detach().cpu()
            for name, value in (
                ("loss_mean", self.loss_mean),
                ("psnr_mean", self.psnr_mean),
                ("reference", self.reference),
            )
        }

    def load_state_dict(self, state: dict) -> None:
        for name in ("loss_mean", "psnr_mean", "reference"):
            value = state.get(name)
            setattr(self, name, None if value is None else value.to(self.device, torch.float32).clone())
