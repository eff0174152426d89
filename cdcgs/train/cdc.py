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
from dataclasses import dataclass

import torch

from .._interop import device_clock
from ..complexity import AGGREGATIONS, METHODS, W_MAX_RULES, ViewComplexity, complexity_over_views
from ..errors import OptionError
from ..neighbors import density
from .presets import build_preset
from .strategy import ADC, StepContext, strategy_option

__all__ = [
    "CDC",
    "Consistency",
    "caat_threshold",
    "correlations",
    "draw",
    "pearson",
    "quantile_score",
    "ranks",
    "zscore",
]


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
    """Pearson's r of two [N] tensors (in float64; 0 when either is constant)."""
    a, b = a.double() - a.double().mean(), b.double() - b.double().mean()
    denominator = (a.norm() * b.norm()).item()
    return (a @ b).item() / denominator if denominator > 0 else 0.0


def ranks(x: torch.Tensor) -> torch.Tensor:
    """[N] float64 ranks 1..N of ``x`` [N], ties sharing their average rank."""
    values, order = torch.sort(x)
    _, group, counts = torch.unique_consecutive(values, return_inverse=True, return_counts=True)
    ends = counts.cumsum(0).double()
    average = ends - (counts.double() - 1.0) / 2.0
    result = torch.empty(x.shape[0], dtype=torch.float64, device=x.device)
    result[order] = average[group]
    return result


# Ψ at or above this counts as saturated: d̄² below about 1e-6, near-duplicate centres (Ψ ≤ 9.1e5).
SATURATED_DENSITY = 5e5


def correlations(gamma: torch.Tensor, psi: torch.Tensor) -> dict:
    """The complexity-density statistics logged at every densification step: Pearson r(Γ, Ψ) (the
    paper's Fig. 4), Pearson r(Γ, log Ψ), Spearman ρ(Γ, Ψ), and the share of saturated Ψ."""
    return {
        "correlation": pearson(gamma, psi),
        "correlation_log_density": pearson(gamma, psi.double().log()),
        "correlation_rank": pearson(ranks(gamma), ranks(psi)),
        "saturated_density": float((psi >= SATURATED_DENSITY).double().mean()),
    }


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
class Consistency:
    """Complexity-density consistency: Γ and Ψ of every Gaussian, their statistics, and the draws
    of densification and pruning candidates; the options are the paper's ablation axes. A mixin:
    :class:`CDC` puts it on 3DGS's ADC, :class:`cdcgs.train.mcmc.MCMC` on 3DGS-MCMC."""

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
    w_max: str = strategy_option(
        "alpha",
        "w_max(p) of Γ: alpha, the largest α over the pixel's tile list (the CDC-GS code), or weight, the largest α·T (the paper's formula)",
        choices=W_MAX_RULES,
    )
    racy_max: bool = strategy_option(
        False,
        "diagnosis: emulate the CDC-GS code's racy per-Gaussian max of Γ (one random pixel per tile instead of the largest)",
    )
    neighbours: int = strategy_option(3, "nearest neighbours that the density Ψ is measured over", low=1, high=16)
    log_correlation: bool = strategy_option(
        True, "log r(Γ, Ψ), r(Γ, log Ψ), Spearman ρ and the share of saturated Ψ at every densification step"
    )

    def __post_init__(self):
        super().__post_init__()
        if self.racy_max and self.pixel_aggregation != "max":
            raise OptionError("--racy-max emulates a racy max: it needs --pixel-aggregation max")

    @property
    def needs_complexity(self) -> bool:
        return self.cdc_densify or self.cdc_prune or self.log_correlation

    @property
    def complexity_maps_method(self) -> str | None:
        return self.complexity_method if self.needs_complexity else None

    def _gamma_options(self, step: int) -> dict:
        return {
            "pixel_aggregation": self.pixel_aggregation,
            "view_aggregation": self.view_aggregation,
            "w_max": self.w_max,
            "racy_max": self.racy_max,
            "racy_seed": step * 100_003,
        }

    def consistency_state(self, model) -> dict:
        """The online schedule's running Γ (empty for the full schedule)."""
        if self.needs_complexity and self.complexity_schedule == "online":
            return {
                "gamma": torch.zeros(model.num, device=model.device),
                "gamma_views": torch.zeros(model.num, device=model.device),
            }
        return {}

    def consistency_statistics(self) -> dict:
        """How the online schedule's running Γ combines across processes (:meth:`statistics`)."""
        if self.needs_complexity and self.complexity_schedule == "online":
            return {"gamma": "max" if self.view_aggregation == "max" else "sum", "gamma_views": "sum"}
        return {}

    def accumulate_complexity(self, ctx: StepContext, state: dict) -> None:
        """Online schedule: add this iteration's render to the running Γ."""
        if self.needs_complexity and self.complexity_schedule == "online":
            with torch.no_grad():
                options = self._gamma_options(ctx.step)
                accumulator = ViewComplexity.from_state(state["gamma"], state["gamma_views"], **options)
                accumulator.add(ctx.info, ctx.complexity_maps[ctx.view_index])

    def complexity(self, ctx: StepContext, state: dict) -> torch.Tensor:
        """[N] Γ of every Gaussian for this densification step."""
        options = self._gamma_options(ctx.step)
        if self.complexity_schedule == "online":
            return ViewComplexity.from_state(state["gamma"], state["gamma_views"], **options).result()
        return complexity_over_views(
            ctx.bins,
            ctx.complexity_maps,
            ctx.model.num,
            ctx.model.device,
            ranks=ctx.ranks,
            groups=ctx.gamma_groups,
            **options,
        )

    def measure(self, ctx: StepContext, state: dict) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """(Γ [N], Ψ [N], a log) of the Gaussians as they are now: the seconds each took
        (``gamma_seconds``, ``psi_seconds``, the device synchronised around each) and, when
        logged, their correlations."""
        device = ctx.model.device
        start = device_clock(device)
        gamma = self.complexity(ctx, state)
        middle = device_clock(device)
        psi = density(ctx.model.params["means"].detach(), self.neighbours)
        log = {"gamma_seconds": middle - start, "psi_seconds": device_clock(device) - middle}
        return gamma, psi, {**(correlations(gamma, psi) if self.log_correlation else {}), **log}

    def consistency_draws(
        self, ctx: StepContext, gamma: torch.Tensor, psi: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """(densify [N], prune [N], log): the Gaussians drawn for consistency densification (complex
        but sparse, ⌊rho_densify N⌋ by |s|) and pruning (flat but crowded, ⌊rho_prune N⌋ by
        1 - opacity), each all False when its part is off."""
        model = ctx.model
        n = model.num
        densify = torch.zeros(n, dtype=torch.bool, device=model.device)
        prune = torch.zeros_like(densify)
        if not (self.cdc_densify or self.cdc_prune):
            return densify, prune, {}
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
        densify_pool, prune_pool = (flat_crowded, complex_sparse) if self.reverse else (complex_sparse, flat_crowded)
        log = {
            "gaussians_before": n,
            "densify_candidates": int(densify_pool.sum()),
            "prune_candidates": int(prune_pool.sum()),
        }
        if self.cdc_densify:
            weights = torch.where(densify_pool, s.abs(), torch.zeros_like(s))
            densify = draw(weights, math.floor(self.rho_densify * n), ctx.generator)
            log["cdc_densify"] = int(densify.sum())
        if self.cdc_prune:
            keep_weight = (1.0 - model.opacities().detach()).clamp_min(1e-12)
            weights = torch.where(prune_pool, keep_weight, torch.zeros_like(keep_weight))
            prune = draw(weights, math.floor(self.rho_prune * n), ctx.generator)
            log["cdc_prune"] = int(prune.sum())
        return densify, prune, log


@dataclass(kw_only=True)
class CDC(Consistency, ADC):
    """ADC plus complexity-density consistency, CAAT and the periodic prune (the options are the
    paper's ablation axes; the defaults are the CDC-GS code's settings)."""

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
    periodic_prune_newborns: bool = strategy_option(
        True,
        "the periodic prune runs after the step's growth and judges the newborn Gaussians too (the CDC-GS code); off: before it",
    )

    # Values are checked by ADC.__post_init__ (check_values), fields of this class included.

    @classmethod
    def from_preset(cls, name: str, options: dict | None = None) -> CDC:
        """The named CDC preset (:data:`cdcgs.train.presets.PRESETS`, aliases accepted) with
        ``options`` overriding its hyperparameters (:func:`cdcgs.train.strategies.make_strategy`
        builds any preset).

        Raises:
            ValueError: an unknown preset or option name, a preset of another class, or a value
                the strategy refuses.
        """
        return build_preset(cls, name, options)

    @property
    def needs_complexity(self) -> bool:
        return Consistency.needs_complexity.fget(self) or self.caat

    def initialize_state(self, model) -> dict:
        return {**super().initialize_state(model), **self.consistency_state(model)}

    # --- hooks --------------------------------------------------------------------------------

    def statistics(self) -> dict:
        return {**super().statistics(), **self.consistency_statistics()}

    def observe(self, ctx: StepContext, state: dict) -> None:
        if self.accumulates_at(ctx.step):
            self.accumulate_complexity(ctx, state)
        super().observe(ctx, state)

    def graph_signature(self, step: int):
        """As ADC's; the online schedule adds each render to Γ with torch operations that read the
        view's complexity map by its index on the host: never captured."""
        if self.needs_complexity and self.complexity_schedule == "online":
            return None
        return super().graph_signature(step)

    def densify_and_prune(self, ctx: StepContext, state: dict) -> dict:
        model = ctx.model
        log = {}
        mean_grad = self.mean_gradient(state)
        prune_extra = None
        threshold = self.grad_threshold
        selected = None
        if self.needs_complexity:
            # Γ, Ψ and the draws over the whole scene; where the Gaussians are sharded, this
            # process's rows of them (every process takes the same decisions over the scene).
            scene, rows = (ctx, slice(None)) if ctx.whole_scene is None else ctx.whole_scene()
            gamma, psi, stats = self.measure(scene, state)
            log.update(stats)
            drawn, prune_extra, draws_log = self.consistency_draws(scene, gamma, psi)
            log.update(draws_log)
            # this slice's rows, copied: the whole scene's tensors go before the surgery
            gamma, drawn, prune_extra = gamma[rows].clone(), drawn[rows].clone(), prune_extra[rows].clone()
            del scene, psi
            if self.caat:
                threshold = caat_threshold(gamma, self.tau_low, self.tau_up, self.caat_lambda)
            selected = (mean_grad >= threshold) | drawn
        else:
            selected = mean_grad >= threshold
        cap, rule = self.growth_cap(ctx, state)
        if cap is not None and rule == "skip" and model.num >= cap and prune_extra is not None:
            prune_extra = torch.zeros_like(prune_extra)  # the CDC-GS code skips the consistency pruning too
        clone, split = self.grow_masks(ctx, state, selected)
        prune_after = None
        if self.periodic_prunes_at(ctx.step):
            # Runs in the densification step, before the opacity reset of the same iteration.
            threshold_opacity = self.periodic_prune_opacity

            def periodic(m):
                mask = m.opacities().detach() < threshold_opacity
                log["periodic_prune"] = int(mask.sum())
                return mask

            if self.periodic_prune_newborns:
                prune_after = periodic
            else:
                prune_extra = periodic(model) if prune_extra is None else prune_extra | periodic(model)
        log.update(self.apply(ctx, state, clone, split, prune_extra, prune_after))
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
