"""The numeric guard of a training: non-finite or exploding numbers stop the run, named.

Every iteration, :meth:`NumericGuard.record` updates two device tensors, the running means of the
loss and the PSNR (which the console shows anyway), and reads nothing back to the host. Non-finite
parameters need no work of their own: the render flags NaN or infinity in the parameters it reads
inside its kernels and reports them with the intersection count it reads anyway (the trainer then
names the update that made them so). The trainer reads the guard, one host synchronisation, with
:meth:`NumericGuard.check` where it reads numbers anyway: at log steps, before a strategy changes
the Gaussians, before an evaluation and before every checkpoint or PLY it writes; the last also
checks every parameter. The check stops the run when the loss's running mean is NaN or infinite,
or exploded: rose above ``EXPLODE_FACTOR`` times the loss of the run's first iteration and above
``EXPLODE_FLOOR`` (a photometric loss of images in [0, 1] stays below 1.2, so only renders far
outside that range reach it). A tripped check raises :class:`TrainingDiverged`, which names what
went wrong and the learning rates in force.

A first version also took every iteration's total gradient norm: on an H100 (2026-11-23) it cost 7% of the
training speed (3000 bonsai iterations at 105.2 against 113.5 it/s, the training being bound by the
host), for NaN gradients that the next render reports anyway.
"""

from __future__ import annotations

import math

import torch

__all__ = ["EXPLODE_FACTOR", "EXPLODE_FLOOR", "NumericGuard", "TrainingDiverged"]

EXPLODE_FACTOR = 4.0
EXPLODE_FLOOR = 1.5
SMOOTHING = 0.9  # running means: m <- 0.9 m + 0.1 x


class TrainingDiverged(RuntimeError):
    """The run's numbers went wrong; nothing of the bad state was written (the message says
    which checkpoint holds the last good one)."""


class NumericGuard:
    """Device-side running means of a run's loss and PSNR, read only by :meth:`check` and
    :meth:`means` (see the module)."""

    def __init__(self, device: torch.device, state: dict | None = None):
        self.device = torch.device(device)
        self.loss_mean: torch.Tensor | None = None  # running means, also what the console shows
        self.psnr_mean: torch.Tensor | None = None
        self.reference: torch.Tensor | None = None  # the loss of the run's first iteration
        if state:
            self.load_state_dict(state)

    def record(self, loss: torch.Tensor, psnr: torch.Tensor, halt: torch.Tensor | None = None) -> None:
        """Add an iteration's loss and PSNR; no host synchronisation. ``halt``: an int32 device
        flag; while its first entry is non-zero the means stay as they are (the iteration is taken
        again later)."""
        loss, psnr = loss.detach().float(), psnr.detach().float()
        if self.loss_mean is None:
            self.loss_mean, self.psnr_mean = loss.clone(), psnr.clone()
        elif halt is None:
            self.loss_mean.lerp_(loss, 1 - SMOOTHING)
            self.psnr_mean.lerp_(psnr, 1 - SMOOTHING)
        else:  # halted: each mean moves towards itself, which leaves it exactly (also for a NaN loss)
            live = halt[0] == 0
            self.loss_mean.lerp_(torch.where(live, loss, self.loss_mean), 1 - SMOOTHING)
            self.psnr_mean.lerp_(torch.where(live, psnr, self.psnr_mean), 1 - SMOOTHING)
        if self.reference is None:
            self.reference = loss.clone()

    def means(self) -> tuple[float, float]:
        """The running means of the loss and the PSNR (a host synchronisation)."""
        if self.loss_mean is None:
            return float("nan"), float("nan")
        loss, psnr = torch.stack([self.loss_mean, self.psnr_mean]).tolist()
        return loss, psnr

    def check(self, step: int, optimizer: torch.optim.Optimizer, params: dict | None = None, last_good: str = ""):
        """Raise :class:`TrainingDiverged` when the loss's running mean is not finite or exploded,
        or (with ``params``, a dict of tensors) a parameter is not finite. One host
        synchronisation. ``last_good`` ends the message: where the last good state is."""
        values = [self.loss_mean.view(1), self.reference.view(1)] if self.loss_mean is not None else []
        names = list(params) if params else []
        if names:
            values.append(
                torch.stack([~torch.isfinite(p.detach()).all() for p in params.values()]).float().to(self.device)
            )
        if not values:
            return
        read = torch.cat(values).tolist()
        causes = []
        if self.loss_mean is not None:
            mean, reference = read[:2]
            read = read[2:]
            if not math.isfinite(mean):
                causes.append(f"the loss became NaN or infinite (its running mean is {mean})")
            elif mean > max(EXPLODE_FACTOR * reference, EXPLODE_FLOOR):
                causes.append(
                    f"the loss exploded (running mean {mean:.4g} at iteration {step}, against {reference:.4g} "
                    "at the first iteration)"
                )
        nonfinite = [name for name, bad in zip(names, read) if bad]
        if nonfinite:
            causes.append(f"the parameters {', '.join(nonfinite)} hold NaN or infinite values")
        if causes:
            raise self.diverged(step, optimizer, "; ".join(causes), last_good)

    def diverged(self, step: int, optimizer, cause: str, last_good: str) -> TrainingDiverged:
        """The error of a run stopped at ``step`` for ``cause``, naming the learning rates."""
        rates = ", ".join(f"{group.get('name', i)} {group['lr']:.3g}" for i, group in enumerate(optimizer.param_groups))
        return TrainingDiverged(
            f"training stopped at iteration {step}: {cause}. The learning rates in force: {rates}; "
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
