"""3DGS-MCMC (Kheradmand et al., NeurIPS 2024), and CDC-GS's consistency draws on top of it.

Gaussians are samples of a distribution, and densification is a Markov chain step rather than a
heuristic. Every ``refine_every`` iterations between ``refine_from`` and ``refine_until``:

- relocation: the dead Gaussians (opacity <= ``dead_opacity``) are moved onto live ones drawn with
  probability proportional to opacity (with replacement). A live Gaussian drawn c times ends as
  n = c + 1 copies at one place, with opacity o' = 1 - (1 - o)^(1/n) and scales
  s' = o / S(n, o') * s, S(n, o') = sum_{i=1}^{n} sum_{k=0}^{i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)
  (the paper's Eq. 9): n copies composite to the original's opacity at its centre and to its
  integrated opacity along a ray, so the rendered image is unchanged in expectation;
- growth: min(budget, (1 + ``growth_rate``) N) - N new Gaussians drawn the same way (copies
  appended), so the count grows 5% per step until it reaches the budget (``target_gaussians``).

After every optimizer step the means get noise R S^2 R^T z * sigmoid(-k (o - t)) * noise_lr * lr
(z ~ N(0, I), lr the current position learning rate): Langevin exploration for transparent
Gaussians, almost none for opaque ones. The loss gets ``opacity_reg`` mean(opacity) +
``scale_reg`` mean(scale). No opacity reset, no gradient threshold.

With the consistency draws on (the ``mcmc-cdc`` preset; the rebuttal says only "CDC densification
and pruning, no CAAT, no periodic prune"), at each refinement step Γ and Ψ are measured as CDC-GS
does; the drawn flat-but-crowded Gaussians join the dead set (relocated, not deleted) and the drawn
complex-but-sparse ones become relocation sources, once each, before the opacity-weighted draws
fill the rest. The count is MCMC's, so it stays at the budget. docs/cdc-gs.md has the design.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import ClassVar

import torch
import warp as wp
from torch.autograd.graph import increment_version

from .._interop import halt_arg, launch, warp_scope, wp_arg
from ..errors import OptionError
from ..kernels.mcmc import mcmc_noise_kernel
from . import ops
from .cdc import Consistency
from .model import GaussianModel
from .strategy import StepContext, StrategyOptions, strategy_option

__all__ = ["MCMC", "copy_weights", "draw_with_replacement", "position_noise", "relocation"]


def draw_with_replacement(weights: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """[count] indices drawn with replacement, with probability proportional to ``weights`` [N]
    (non-negative, some positive): uniforms from ``generator`` inverted through the cumulative sum.

    Unlike ``torch.multinomial``, every run and every process draws the same indices from the same
    weights and generator state: the cumulative sum is taken on the host, in float64, where CUDA's
    scan (which ``torch.multinomial`` uses) may round differently from one run to the next
    (pytorch/pytorch#75240). The processes of a data-parallel run relocate by these draws, and two
    that drew differently no longer train one model (seen on two GPUs at 6M Gaussians)."""
    host = weights.detach().cpu().double()
    cdf = host.cumsum(0)
    total = float(cdf[-1]) if cdf.numel() else 0.0
    if not total > 0.0 or not math.isfinite(total) or bool((host < 0).any()):
        raise ValueError(
            f"draw_with_replacement: the weights must be finite, non-negative and not all zero (sum {total})"
        )
    last = int(torch.searchsorted(cdf, cdf[-1:]))  # the last positive weight (a guard: u < 1 keeps u * total < total)
    u = torch.rand(count, dtype=torch.float64, device=weights.device, generator=generator) * total
    drawn = torch.searchsorted(cdf.to(weights.device), u, right=True)  # the first i with cdf[i] > u
    return drawn.clamp_(max=last)


def copy_weights(max_copies: int, dtype=torch.float64, device="cpu") -> torch.Tensor:
    """[max_copies, max_copies] W with W[n-1, k] = sum_{i=1}^{n} C(i-1, k) (-1)^k / sqrt(k+1), so
    that S(n, o') = sum_k W[n-1, k] o'^(k+1)."""
    return _copy_weights(max_copies).to(dtype=dtype, device=device, copy=True)  # the cached table stays as it is


@functools.cache
def _copy_weights(max_copies: int) -> torch.Tensor:
    terms = torch.zeros(max_copies, max_copies, dtype=torch.float64)
    for i in range(max_copies):  # i = (row i of the sum) - 1
        for k in range(i + 1):
            terms[i, k] = math.comb(i, k) * (-1.0) ** k / math.sqrt(k + 1)
    return terms.cumsum(0)


def relocation(
    opacities: torch.Tensor, scales: torch.Tensor, copies: torch.Tensor, weights: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(opacity [M], scales [M, 3]) of each of n = ``copies`` [M] Gaussians that replace one of
    opacity ``opacities`` [M] and scales ``scales`` [M, 3] at the same place (3DGS-MCMC Eq. 9),
    computed in float64. ``weights``: :func:`copy_weights` (its size caps n)."""
    n = copies.long().clamp(1, weights.shape[0])
    o = opacities.double()
    new_opacity = 1.0 - (1.0 - o) ** (1.0 / n.double())
    powers = new_opacity[:, None] ** torch.arange(1, weights.shape[0] + 1, device=o.device, dtype=torch.float64)
    total = (powers * weights.to(o.device)[n - 1]).sum(-1)
    new_scales = (o / total)[:, None] * scales.double()
    return new_opacity, new_scales


def position_noise(
    model: GaussianModel,
    lr: float,
    noise_lr: float,
    k: float,
    t: float,
    generator: torch.Generator,
    out: torch.Tensor | None = None,
    halt: torch.Tensor | None = None,
) -> torch.Tensor:
    """[N, 3] 3DGS-MCMC's perturbation of the means: Σ z sigmoid(-k (o - t)) noise_lr lr, with
    Σ = R S^2 R^T of each Gaussian and z ~ N(0, I) drawn from ``generator``; added to ``out``
    ([N, 3] float32, e.g. the means) when given, and returned. One kernel
    (:data:`cdcgs.kernels.mcmc.mcmc_noise_kernel`) after the draw; nothing is added while
    ``halt`` (an int32 device flag) is set."""
    params = model.params
    z = torch.randn(model.num, 3, device=model.device, generator=generator)
    target = torch.zeros_like(z) if out is None else out
    if (
        target.shape != z.shape
        or target.dtype != torch.float32
        or not target.is_contiguous()
        or target.device != z.device
    ):
        raise ValueError(f"position_noise: out must be a contiguous float32 [{model.num}, 3] tensor on {z.device}")
    with warp_scope(model.device):
        launch(
            mcmc_noise_kernel,
            model.num,
            inputs=[
                wp_arg(params["quats"].detach(), wp.vec4),
                wp_arg(params["log_scales"].detach(), wp.vec3),
                wp_arg(params["opacity_logits"].detach(), wp.float32),
                wp_arg(z, wp.vec3),
                float(k),
                float(t),
                float(noise_lr * lr),
                halt_arg(halt, model.device),
            ],
            outputs=[wp_arg(target, wp.vec3)],
        )
    increment_version(target)  # written through its address: what an in-place op would say
    return target


@dataclass(kw_only=True)
class MCMC(Consistency, StrategyOptions):
    """3DGS-MCMC, with CDC-GS's consistency draws as an option (on by default in this class; the
    ``mcmc`` preset turns them off, ``mcmc-cdc`` keeps them)."""

    # The 3DGS-MCMC code's: opacity 0.5, 3DGS's arithmetic-mean scales times 0.1, opacity learning
    # rate 0.05 (its create_from_pcd and arguments; gsplat's mcmc settings agree).
    training_defaults: ClassVar[dict] = {
        "init_opacity": 0.5,
        "scale_rule": "3dgs",
        "init_scale": 0.1,
        "opacity_lr": 0.05,
    }

    target_gaussians: int | None = strategy_option(
        None, "the budget: the count grows to it and stays (3DGS-MCMC's cap_max)", low=1
    )
    refine_from: int = strategy_option(500, "first relocation and growth after this iteration", low=0)
    refine_until: int = strategy_option(25_000, "relocate and grow before this iteration (not at it)", low=0)
    refine_every: int = strategy_option(100, "iterations between relocation and growth steps", low=1)
    growth_rate: float = strategy_option(
        0.05, "each growth step adds this fraction of N, up to the budget", low=0.0, low_open=True
    )
    dead_opacity: float = strategy_option(
        0.005, "Gaussians at or below this opacity are dead: relocated onto live ones", low=0.0, high=1.0
    )
    max_copies: int = strategy_option(
        51, "a Gaussian relocated to more than this many copies counts as this many", low=1
    )
    noise_lr: float = strategy_option(5e5, "scale of the position noise, times the position learning rate", low=0.0)
    noise_k: float = strategy_option(100.0, "steepness k of the noise gate sigmoid(-k (opacity - t))", low=0.0)
    noise_t: float = strategy_option(0.005, "opacity t at which the noise gate is one half", low=0.0, high=1.0)
    noise_until: int | None = strategy_option(
        None, "no position noise from this iteration on (none: noise to the end)", low=1
    )
    opacity_reg: float = strategy_option(0.01, "loss weight of the mean opacity (L1)", low=0.0)
    scale_reg: float = strategy_option(0.01, "loss weight of the mean scale (L1)", low=0.0)
    reset_target_moments: bool = strategy_option(
        False,
        "zero the Adam moments of the dead Gaussians' slots that relocation fills (the 3DGS-MCMC code and gsplat zero only the sources')",
    )

    def __post_init__(self):
        super().__post_init__()
        if self.target_gaussians is None:
            raise OptionError("3DGS-MCMC needs a budget: --target-gaussians N (its final count)")

    def initialize_state(self, model: GaussianModel) -> dict:
        return self.consistency_state(model)

    def check(self, total_steps: int) -> None:
        pass

    # --- the schedule -------------------------------------------------------------------------

    def refines_at(self, step: int) -> bool:
        """Whether iteration ``step`` relocates and grows (600, 700, ..., 24900 by default)."""
        return self.refine_from < step < self.refine_until and step % self.refine_every == 0

    def accumulates_at(self, step: int) -> bool:
        return step < self.refine_until

    # --- hooks --------------------------------------------------------------------------------

    def before_backward(self, ctx: StepContext, state: dict) -> None:
        pass

    def regularizer(self, ctx: StepContext) -> torch.Tensor | None:
        if self.opacity_reg == 0 and self.scale_reg == 0:
            return None
        model = ctx.model
        return self.opacity_reg * model.opacities().mean() + self.scale_reg * model.scales().mean()

    def statistics(self) -> dict:
        return self.consistency_statistics()

    def graph_signature(self, step: int):
        """What a captured step (``--cuda-graph``) of iteration ``step`` depends on in these hooks:
        nothing that changes between two relocations. The regulariser is device operations on the
        Gaussians, captured with the loss; the position noise is drawn and added in
        :meth:`after_step`, which the trainer calls after the replay, eagerly, from the step's
        generator and the position learning rate of the host, as without graphs. The online Γ
        (``mcmc-cdc --complexity-schedule online``) reads each view's map by its index on the
        host: never captured."""
        if self.needs_complexity and self.complexity_schedule == "online":
            return None
        return True

    def observe(self, ctx: StepContext, state: dict) -> None:
        if self.accumulates_at(ctx.step):
            self.accumulate_complexity(ctx, state)

    def refine(self, ctx: StepContext, state: dict) -> dict:
        with torch.no_grad():
            log = self.relocate(ctx, state)
            log.update(self.grow(ctx))
        state.update(self.initialize_state(ctx.model))
        log["gaussians"] = ctx.model.num
        return log

    def after_step(self, ctx: StepContext, state: dict) -> None:
        if self.noise_until is not None and ctx.step >= self.noise_until:
            return
        lr = next(g["lr"] for g in ctx.optimizer.param_groups if g["name"] == "means")
        with torch.no_grad():  # added to the means in place
            means = ctx.model.params["means"].detach()
            position_noise(
                ctx.model, lr, self.noise_lr, self.noise_k, self.noise_t, ctx.generator, out=means, halt=ctx.halt
            )

    # --- pieces -------------------------------------------------------------------------------

    def _weights(self, device) -> torch.Tensor:
        return copy_weights(self.max_copies, device=device)

    def _copy(self, ctx: StepContext, sources: torch.Tensor) -> dict:
        """New pre-activation opacity and log-scales of each source [M] (indices, repeats counted)."""
        model = ctx.model
        copies = torch.bincount(sources, minlength=model.num)[sources] + 1
        opacity, scales = relocation(
            model.opacities().detach()[sources], model.scales().detach()[sources], copies, self._weights(model.device)
        )
        opacity = opacity.clamp(self.dead_opacity, 1.0 - torch.finfo(torch.float32).eps)
        return {"opacity_logits": torch.logit(opacity).float(), "log_scales": scales.log().float()}

    def relocate(self, ctx: StepContext, state: dict) -> dict:
        """Move the dead Gaussians (and with the consistency draws, the drawn flat-but-crowded)
        onto sources: the drawn complex-but-sparse first, then live ones by opacity."""
        model = ctx.model
        opacity = model.opacities().detach()
        dead = opacity <= self.dead_opacity
        log = {}
        favoured = torch.zeros_like(dead)
        if self.needs_complexity:
            gamma, psi, stats = self.measure(ctx, state)
            log.update(stats)
            favoured, crowded, draws_log = self.consistency_draws(ctx, gamma, psi)
            log.update(draws_log)
            dead |= crowded
            favoured &= ~dead
        n_dead = int(dead.sum())
        alive = ~dead
        if n_dead == 0 or not bool(alive.any()):
            log["relocated"] = 0
            return log
        log["relocated"] = n_dead
        targets = dead.nonzero()[:, 0]
        first = favoured.nonzero()[:, 0]
        first = first[torch.randperm(first.shape[0], device=first.device, generator=ctx.generator)[:n_dead]]
        rest = n_dead - first.shape[0]
        alive_index = alive.nonzero()[:, 0]
        sources = first
        if rest > 0:
            drawn = draw_with_replacement(opacity[alive_index], rest, ctx.generator)
            sources = torch.cat([first, alive_index[drawn]])
        ops.relocate(
            model, ctx.optimizer, targets, sources, self._copy(ctx, sources), restart_targets=self.reset_target_moments
        )
        return log

    def grow(self, ctx: StepContext) -> dict:
        """Add min(budget, (1 + growth_rate) N) - N copies of Gaussians drawn by opacity."""
        model = ctx.model
        target = min(self.target_gaussians, int((1.0 + self.growth_rate) * model.num))
        count = max(0, target - model.num)
        if count == 0:
            return {"added": 0}
        sources = draw_with_replacement(model.opacities().detach(), count, ctx.generator)
        values = self._copy(ctx, sources)
        ops.relocate(model, ctx.optimizer, sources, sources, values)  # the sources' new opacity and scales
        ops.append(model, ctx.optimizer, {name: p.detach()[sources] for name, p in model.params.items()})
        return {"added": count}
