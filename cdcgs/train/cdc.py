"""CDC-GS: complexity-density consistent densification (Dong et al., NeurIPS 2025), on ADC.

At each densification step (the 3DGS schedule) every Gaussian gets a complexity Gamma (how much
high-frequency image content it is responsible for, ``cdcgs.complexity``) and a density Psi
(1 / geometric mean of its squared distances to its 3 nearest neighbours, exact KNN). Their
z-scores multiply into a consistency score s = z(Gamma) z(Psi):

- s < 0 and z(Gamma) > 0, complex but sparse: densification candidates, drawn (rho_densify x N,
  without replacement, probability proportional to |s|) into the gradient-selected set;
- s < 0 and z(Gamma) < 0, flat but crowded: pruning candidates, drawn (rho_prune x N,
  probability proportional to 1 - opacity) and removed.

CAAT lowers the gradient threshold of complex Gaussians; the periodic prune (every 3000 steps,
opacity < 0.1) replaces the per-step 3DGS pruning, as in the authors' code. Every variant of the
paper, and the 3DGS baseline, is a configuration of this one class (:mod:`cdcgs.train.presets`,
:meth:`CDC.from_preset`); docs/cdc-gs.md has the details.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from ..complexity import AGGREGATIONS, METHODS, ViewComplexity, complexity_over_views
from ..errors import OptionError
from ..neighbors import density
from .presets import PRESETS, canonical_name
from .strategy import ADC, StepContext, strategy_option

__all__ = ["CDC", "caat_threshold", "draw", "pearson", "quantile_score", "zscore"]


def zscore(x: torch.Tensor) -> torch.Tensor:
    return (x - x.mean()) / (x.std() + 1e-6)


def quantile_score(x: torch.Tensor, q: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Like the z-score, centred on the q-quantile instead of the mean (CDC-GS's compact variant).

    Above a million values the quantile is estimated from a million drawn with ``generator``
    (torch.quantile's limit)."""
    if x.numel() <= 1_000_000:
        sample = x
    else:
        sample = x[torch.randperm(x.numel(), device=x.device, generator=generator)[:1_000_000]]
    return (x - torch.quantile(sample.float(), q)) / (x.std() + 1e-6)


def pearson(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.double() - a.double().mean(), b.double() - b.double().mean()
    denominator = (a.norm() * b.norm()).item()
    return (a @ b).item() / denominator if denominator > 0 else 0.0


def caat_threshold(gamma: torch.Tensor, tau_low: float, tau_up: float, lam: float) -> torch.Tensor:
    """tau(Gamma) = tau_low + (tau_up - tau_low)(1 - 2(sigmoid(lam Gamma) - 0.5)), Gamma in [0, 1]."""
    g = gamma.clamp(0.0, 1.0)
    return tau_low + (tau_up - tau_low) * (1.0 - 2.0 * (torch.sigmoid(lam * g) - 0.5))


def draw(weights: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """[N] mask of ``count`` indices drawn without replacement with probability proportional to
    ``weights`` (all the positive ones when there are fewer)."""
    mask = torch.zeros(weights.shape[0], dtype=torch.bool, device=weights.device)
    positive = weights > 0
    available = int(positive.sum())
    if count <= 0 or available == 0:
        return mask
    if count >= available:
        return positive
    mask[torch.multinomial(weights.float(), count, replacement=False, generator=generator)] = True
    return mask


@dataclass(kw_only=True)
class CDC(ADC):
    """ADC plus complexity-density consistency (the options are the paper's ablation axes)."""

    cdc_densify: bool = strategy_option(
        True, "draw complex-but-sparse Gaussians into densification (consistency densification)"
    )
    cdc_prune: bool = strategy_option(True, "draw flat-but-crowded Gaussians for removal (consistency pruning)")
    rho_densify: float = strategy_option(0.01, "consistency densification draws this fraction of N", low=0.0, high=1.0)
    rho_prune: float = strategy_option(0.01, "consistency pruning draws this fraction of N", low=0.0, high=1.0)
    reverse: bool = strategy_option(False, "sanity ablation: densify the flat-crowded, prune the complex-sparse")
    centre: str = strategy_option(
        "mean",
        "centres of the Γ and Ψ scores: mean (z-scores) or quantile (compact variant)",
        choices=("mean", "quantile"),
    )
    complexity_quantile: float = strategy_option(
        0.75, "with --centre quantile: the quantile of Γ that centres its score", low=0.0, high=1.0
    )
    density_quantile: float = strategy_option(
        0.25, "with --centre quantile: the quantile of Ψ that centres its score", low=0.0, high=1.0
    )
    caat: bool = strategy_option(
        True, "CAAT: complexity-aware adaptive gradient threshold between --tau-low and --tau-up"
    )
    tau_low: float = strategy_option(1.5e-4, "CAAT: threshold of the most complex Gaussians", low=0.0)
    tau_up: float = strategy_option(2e-4, "CAAT: threshold of the flattest Gaussians", low=0.0)
    caat_lambda: float = strategy_option(6.0, "CAAT: steepness λ of the sigmoid in Γ")
    periodic_prune: bool = strategy_option(
        True,
        "every --periodic-prune-every steps remove Gaussians below --periodic-prune-opacity (replaces per-step pruning)",
    )
    periodic_prune_every: int = strategy_option(3000, "iterations between periodic prunes", low=1)
    periodic_prune_opacity: float = strategy_option(
        0.1, "the periodic prune removes Gaussians less opaque than this", low=0.0, high=1.0
    )
    complexity_schedule: str = strategy_option(
        "full",
        "full: Γ over every training view at each densification step (as the paper); online: from the training renders since the last step",
        choices=("full", "online"),
    )
    pixel_aggregation: str = strategy_option(
        "max", "Γ within a view: max or mean over the pixels a Gaussian composites", choices=AGGREGATIONS
    )
    view_aggregation: str = strategy_option(
        "max", "Γ across views: max, or mean over the views that see the Gaussian", choices=AGGREGATIONS
    )
    complexity_method: str = strategy_option(
        "dwt", "high-frequency map: Haar DWT (1 or 2 levels) or an edge filter", choices=METHODS
    )
    neighbours: int = strategy_option(3, "nearest neighbours that the density Ψ is measured over", low=1, high=16)
    log_correlation: bool = strategy_option(True, "log Pearson r(Γ, Ψ) at every densification step (correlation.png)")

    # Values are checked by ADC.__post_init__ (check_values), fields of this class included.

    @classmethod
    def from_preset(cls, name: str, options: dict | None = None) -> CDC:
        """The named preset (:data:`cdcgs.train.presets.PRESETS`, aliases accepted) with
        ``options`` overriding its hyperparameters.

        Raises:
            ValueError: an unknown preset or option name, or a value the strategy refuses.
        """
        preset = PRESETS[canonical_name(name)]
        options = dict(options or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise OptionError(f"strategy {name!r} has no option(s) {unknown}; it has {sorted(known)}")
        return cls(**{**preset, **options})

    @property
    def needs_complexity(self) -> bool:
        return self.cdc_densify or self.cdc_prune or self.caat or self.log_correlation

    @property
    def complexity_maps_method(self) -> str | None:
        return self.complexity_method if self.needs_complexity else None

    def _aggregation(self) -> dict:
        return {"pixel_aggregation": self.pixel_aggregation, "view_aggregation": self.view_aggregation}

    def initialize_state(self, model) -> dict:
        state = super().initialize_state(model)
        if self.needs_complexity and self.complexity_schedule == "online":
            state["gamma"] = torch.zeros(model.num, device=model.device)
            state["gamma_views"] = torch.zeros(model.num, device=model.device)
        return state

    def complexity(self, ctx: StepContext, state: dict) -> torch.Tensor:
        """[N] Γ of every Gaussian for this densification step."""
        if self.complexity_schedule == "online":
            return ViewComplexity.from_state(state["gamma"], state["gamma_views"], **self._aggregation()).result()
        return complexity_over_views(
            ctx.render, ctx.complexity_maps, ctx.model.num, ctx.model.device, **self._aggregation()
        )

    # --- hooks --------------------------------------------------------------------------------

    def after_backward(self, ctx: StepContext, state: dict) -> dict:
        if self.needs_complexity and self.complexity_schedule == "online" and self.accumulates_at(ctx.step):
            with torch.no_grad():
                accumulator = ViewComplexity.from_state(state["gamma"], state["gamma_views"], **self._aggregation())
                accumulator.add(ctx.info, ctx.complexity_maps[ctx.view_index])
        return super().after_backward(ctx, state)

    def densify_and_prune(self, ctx: StepContext, state: dict) -> dict:
        model = ctx.model
        log = {}
        mean_grad = self.mean_gradient(state)
        selected_by_gradient = None
        prune_extra = torch.zeros(model.num, dtype=torch.bool, device=model.device)
        if self.needs_complexity:
            gamma = self.complexity(ctx, state)
            psi = density(model.params["means"].detach(), self.neighbours)
            if self.log_correlation:
                log["correlation"] = pearson(gamma, psi)
            threshold = (
                caat_threshold(gamma, self.tau_low, self.tau_up, self.caat_lambda) if self.caat else self.grad_threshold
            )
            selected_by_gradient = mean_grad >= threshold
            if self.cdc_densify or self.cdc_prune:
                if self.centre == "mean":
                    z_gamma, z_psi = zscore(gamma), zscore(psi)
                else:
                    z_gamma, z_psi = (
                        quantile_score(gamma, self.complexity_quantile, ctx.generator),
                        quantile_score(psi, self.density_quantile, ctx.generator),
                    )
                s = z_gamma * z_psi
                complex_sparse = (s < 0) & (z_gamma > 0)
                flat_crowded = (s < 0) & (z_gamma < 0)
                densify_pool, prune_pool = (
                    (flat_crowded, complex_sparse) if self.reverse else (complex_sparse, flat_crowded)
                )
                n = model.num
                log.update(
                    gaussians_before=n,
                    densify_candidates=int(densify_pool.sum()),
                    prune_candidates=int(prune_pool.sum()),
                )
                if self.cdc_densify:
                    drawn = draw(
                        torch.where(densify_pool, s.abs(), torch.zeros_like(s)),
                        math.floor(self.rho_densify * n),
                        ctx.generator,
                    )
                    log["cdc_densify"] = int(drawn.sum())
                    selected_by_gradient |= drawn
                if self.cdc_prune:
                    keep_weight = (1.0 - model.opacities().detach()).clamp_min(1e-12)
                    prune_extra = draw(
                        torch.where(prune_pool, keep_weight, torch.zeros_like(keep_weight)),
                        math.floor(self.rho_prune * n),
                        ctx.generator,
                    )
                    log["cdc_prune"] = int(prune_extra.sum())
        else:
            selected_by_gradient = mean_grad >= self.grad_threshold
        clone, split = self.grow_masks(ctx, state, selected_by_gradient)
        if self.periodic_prunes_at(ctx.step):
            # Runs in the densification step, before the opacity reset of the same iteration.
            prune_extra |= model.opacities().detach() < self.periodic_prune_opacity
            log["periodic_prune"] = int((model.opacities().detach() < self.periodic_prune_opacity).sum())
        log.update(self.apply(ctx, state, clone, split, prune_extra))
        return log

    def periodic_prunes_at(self, step: int) -> bool:
        """Whether iteration ``step`` runs the periodic prune: a densification step that is a
        multiple of ``periodic_prune_every`` (3000, 6000, 9000, 12000 by default)."""
        return self.periodic_prune and self.densifies_at(step) and step % self.periodic_prune_every == 0

    def prune_mask(self, ctx: StepContext, max_radius: torch.Tensor) -> torch.Tensor:
        if self.periodic_prune:
            # The authors' code replaces the per-step 3DGS pruning by the periodic prune.
            return torch.zeros(ctx.model.num, dtype=torch.bool, device=ctx.model.device)
        return super().prune_mask(ctx, max_radius)
