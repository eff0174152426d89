"""Densification strategies: the hooks every strategy offers, what they may touch, and 3DGS's
adaptive density control (:class:`ADC`), on which CDC-GS (:mod:`cdcgs.train.cdc`) builds.

A strategy is configuration plus functions. The trainer owns everything that changes: the model,
the optimizer, the generator, the complexity-map cache, and the strategy's own state (a dict of
tensors and numbers from ``initialize_state``, saved in checkpoints and restored on resume). The
trainer calls the same hooks on every strategy and never asks which one it has. Parameter and
optimizer-state surgery is in :mod:`cdcgs.train.ops`; named presets in :mod:`cdcgs.train.presets`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from typing import Any, ClassVar, Protocol, runtime_checkable

import torch

from ..errors import OptionError
from . import ops
from .config import check_values, option
from .model import GaussianModel
from .schedules import DASH_MOMENTUM_START, dash_budget, dash_momentum

__all__ = ["ADC", "StepContext", "Strategy", "StrategyOptions", "strategy_option"]


# A strategy hyperparameter: a dataclass field with its help line, choices or range (as the
# configuration's options), which the command line shows and check_values enforces.
strategy_option = option


@dataclass
class StepContext:
    """What a strategy may look at, and change, during one training iteration.

    A hook may change ``model`` and ``optimizer`` only through :mod:`cdcgs.train.ops`, draw random
    numbers only from ``generator``, and render (``render``) and read ``views`` and
    ``complexity_maps`` but not change them. Everything else is read-only.
    """

    step: int  # 1-based iteration number of the step being taken
    total_steps: int
    model: GaussianModel
    optimizer: torch.optim.Optimizer
    info: Any  # the RasterizeInfo of this iteration's render (None in ``refine``)
    view_index: int | None  # index of the rendered view in the training views (None in ``refine``)
    extent: float
    generator: torch.Generator  # on the model's device: every random draw of a strategy uses it
    render: Callable | None = None  # render(view_index) -> (image, alpha, info) of a training view
    # bins(view_index) -> PendingBins of a training view's tile lists (no image); .finish() gives its RasterizeInfo
    bins: Callable | None = None
    # a Γ pass's views measured from one CUDA graph (cdcgs.train.graph.GammaGroups), or None
    gamma_groups: Any = None
    views: list | None = None  # the training views (with their images)
    complexity_maps: Any = None  # cdcgs.complexity.ComplexityMaps of the training views, owned by the run
    ranks: Any = None  # cdcgs.train.distributed.Ranks of a run on several processes (None: one process)
    resolution_scale: int | None = None  # the downscale this iteration renders at (None: no --resolution-schedule)
    # --sync-free: an int32 device flag; while set, no hook may change anything on the device (the
    # step is taken again later). Pass it to the kernels that take ``halt``. None: never set.
    halt: Any = None
    # --dist-mode shards, in ``refine``: whole_scene() -> (a context whose ``model`` is the whole
    # scene's geometry, gathered from every process's slice, with ``bins``, ``ranks`` and a
    # ``generator`` that every process shares; the slice of its rows that ``model`` here holds).
    # Decisions over the whole scene (CDC-GS's Γ, Ψ and draws) are taken there, the same on every
    # process. None: the model is the whole scene.
    whole_scene: Callable | None = None


@runtime_checkable
class Strategy(Protocol):
    """The hooks the trainer calls, in this order within a step.

    A step renders a batch of views (``--batch-size``, one by default; on several processes each
    renders its share), one iteration per view, and then updates the Gaussians once. For each
    view of the process, with ``ctx.step`` that view's iteration:

    - ``before_backward(ctx, state)``: after the render, before ``loss.backward()`` (ask the
      render for the gradients the strategy needs, e.g. ``ctx.info.retain_absgrad()``).
    - ``regularizer(ctx) -> Tensor | None``: a term added to the view's loss (None: nothing),
      e.g. 3DGS-MCMC's opacity and scale penalties.
    - ``observe(ctx, state)``: after the view's backward: add to the statistics in ``state``
      (gradient sums, counts, maxima, the online Γ); nothing else.

    Then, once per step, after the gradients and the statistics of every view and every process
    are summed (``statistics`` says how each key of ``state`` combines across processes):

    - ``refine(ctx, state) -> dict``: for each iteration of the step where ``refines_at`` holds
      (``ctx.info`` and ``ctx.view_index`` are None): change the Gaussians (densify, prune,
      reset, relocate; only via :mod:`cdcgs.train.ops`), before the optimizer step; returns
      numbers worth logging.
    - ``after_step(ctx, state)``: after the optimizer step, with the step's last iteration
      (e.g. 3DGS-MCMC's position noise).

    And:

    - ``initialize_state(model) -> dict``: the strategy's state for a new run, and again whenever
      the strategy resets it. The trainer keeps the dict, checkpoints it and hands it back.
    - ``statistics() -> dict``: the keys of ``state`` that ``observe`` adds to, each with how the
      processes' values combine: ``"sum"`` or ``"max"``.
    - ``refines_at(step) -> bool``: whether ``refine`` acts at iteration ``step`` (the trainer
      checks the run's numbers first, so that no strategy works on NaN).
    - ``config() -> dict``: the name and hyperparameters, for config.json and metrics.json.
    - ``complexity_maps_method``: the method (cdcgs.complexity.METHODS) of the complexity maps
      that the hooks read from ``ctx.complexity_maps``, or None when they read none.
    - ``training_defaults``: the values of the training options that a run leaves at none
      (``init_opacity``, ``scale_rule``, ``init_scale``, ``opacity_lr``), e.g. 3DGS-MCMC's.
    - ``check(total_steps)``: refuse (OptionError) options that cannot act in a run of that length.

    :class:`StrategyOptions` adds ``after_backward(ctx, state)``, ``observe`` then ``refine``
    where it acts: the one-view, one-process step in one call.
    """

    complexity_maps_method: str | None
    training_defaults: dict

    def initialize_state(self, model: GaussianModel) -> dict: ...

    def before_backward(self, ctx: StepContext, state: dict) -> None: ...

    def regularizer(self, ctx: StepContext) -> torch.Tensor | None: ...

    def observe(self, ctx: StepContext, state: dict) -> None: ...

    def statistics(self) -> dict: ...

    def refines_at(self, step: int) -> bool: ...

    def refine(self, ctx: StepContext, state: dict) -> dict: ...

    def after_step(self, ctx: StepContext, state: dict) -> None: ...

    def check(self, total_steps: int) -> None: ...

    def config(self) -> dict: ...


class StrategyOptions:
    """What every strategy dataclass shares: its options checked on construction, listed, and
    recorded with its name."""

    def __post_init__(self):
        check_values(self)

    def config(self) -> dict:
        return {"name": type(self).__name__, **asdict(self)}

    @classmethod
    def options(cls) -> list:
        """The hyperparameters: dataclass fields with their help (``metadata``)."""
        return list(fields(cls))

    def after_backward(self, ctx: StepContext, state: dict) -> dict:
        """One view's step on one process: ``observe``, then ``refine`` where it acts."""
        self.observe(ctx, state)
        return self.refine(ctx, state) if self.refines_at(ctx.step) else {}


@dataclass(kw_only=True)
class ADC(StrategyOptions):
    """3DGS adaptive density control (Kerbl et al. 2023), with the AbsGS variant as an option.

    Accumulates the norm of each Gaussian's screen-space positional gradient (NDC units) over the
    views that saw it. Every ``densify_every`` steps after ``densify_from`` and before
    ``densify_until`` (iterations count from 1, and the end is excluded, as in the INRIA code: 600,
    700, ..., 14900 by default; :meth:`densifies_at`): Gaussians
    whose mean gradient reaches ``grad_threshold`` are cloned when small (max scale <=
    ``clone_max_scale`` x extent) and split into ``split_count`` when large; Gaussians with opacity
    below ``prune_opacity`` are removed, and after the first opacity reset also those larger than
    ``prune_world_size`` x extent (and than ``prune_screen_size`` px when that is set). Opacities
    are reset to ``reset_value`` every ``reset_every`` steps before ``densify_until`` (3000, ...,
    12000; :meth:`resets_at`).

    The 3DGS paper also prunes Gaussians over 20 px on screen, but its code zeroes the screen radii
    (``densification_postfix``) before that test, so the rule never fires; its authors confirm the
    published results were made that way (graphdeco-inria/gaussian-splatting issues 123 and 643),
    and the CDC-GS code inherits it. So ``prune_screen_size`` is 0 (off) by default; 20 gives the
    rule as written, which cost 0.75 dB of test PSNR on bonsai (docs/cdc-gs.md).

    ``budget_schedule="dash"`` caps growth at DashGaussian's primitive budget
    (:func:`cdcgs.train.schedules.dash_budget`), which rises with the resolution of
    ``--resolution-schedule dash`` (``ctx.resolution_scale``) to ``budget_max``, or without it to
    the initial count plus DashGaussian's momentum (:func:`cdcgs.train.schedules.dash_momentum`,
    fed with the number of Gaussians each densification step selects). The strongest candidates
    that fit grow, as with ``cap_rule="fill"``. Growth comes before pruning here (3DGS's order),
    so unlike DashGaussian, which prunes first, the Gaussians a step prunes do not make room in it.
    """

    grad_threshold: float = strategy_option(
        2e-4, "densify Gaussians whose mean screen-space positional gradient (NDC) reaches this", low=0.0
    )
    absgrad: bool = strategy_option(
        False, "AbsGS statistic: sum of per-pixel absolute gradients (use a higher threshold)"
    )
    densify_from: int = strategy_option(500, "first densification after this iteration", low=0)
    densify_until: int = strategy_option(
        15_000, "densify, reset opacity and accumulate statistics before this iteration (not at it)", low=0
    )
    densify_every: int = strategy_option(100, "iterations between densification steps", low=1)
    reset_every: int = strategy_option(3000, "iterations between opacity resets", low=1)
    reset_value: float = strategy_option(
        0.01, "opacity resets clamp every opacity to at most this", low=0.0, high=1.0, low_open=True
    )
    prune_opacity: float = strategy_option(
        0.005, "prune Gaussians less opaque than this at each densification step", low=0.0, high=1.0
    )
    clone_max_scale: float = strategy_option(
        0.01, "clone (not split) selected Gaussians whose largest scale is at most this x extent", low=0.0
    )
    split_count: int = strategy_option(2, "children that replace a split Gaussian", low=2)
    split_scale_divisor: float = strategy_option(
        1.6, "children's scales are the parent's divided by this", low=0.0, low_open=True
    )
    prune_screen_size: float = strategy_option(
        0.0,
        "after the first reset, prune Gaussians larger than this many pixels on screen (0: off, as the 3DGS code runs)",
        low=0.0,
    )
    prune_world_size: float = strategy_option(
        0.1, "after the first reset, prune Gaussians larger than this x extent", low=0.0, low_open=True
    )
    max_gaussians: int | None = strategy_option(
        None, "a cap on the count for densification (see --cap-rule; --target-gaussians lands on a count)", low=1
    )
    cap_rule: str = strategy_option(
        "skip",
        "with --max-gaussians: skip (no growth once the count has reached the cap, as the CDC-GS code's --gs_num; "
        "a step may pass it) or fill (grow the strongest candidates that fit)",
        choices=("skip", "fill"),
    )
    target_gaussians: int | None = strategy_option(
        None,
        "end with exactly this many Gaussians: growth is capped at it (strongest first) and the last "
        "densification step clones the strongest remaining or prunes the least opaque to land on it "
        "(3DGS-MCMC: its budget)",
        low=1,
    )
    budget_schedule: str = strategy_option(
        "none",
        "none, or dash: DashGaussian's primitive budget, growth capped (strongest first) at a count that rises with "
        "the resolution of --resolution-schedule dash to --budget-max (not exact: off by default)",
        choices=("none", "dash"),
    )
    budget_max: int | None = strategy_option(
        None,
        "with --budget-schedule dash: the count the budget rises to (none: DashGaussian's estimate, the initial "
        "count plus a momentum that follows the Gaussians each densification step selects)",
        low=1,
    )

    gaussian_order: str = strategy_option(
        "auto",
        "the Gaussians' order in memory after each densification step: morton (sorted by the Morton code of their "
        "means, so that neighbours in space are neighbours in memory: a faster step), appended (the grown after "
        "the others, as 3DGS), or auto (morton, except on --dist-mode shards, where it is appended: there morton "
        "sorts each process's slice, measured no faster)",
        choices=("auto", "morton", "appended"),
    )

    # The training options a run leaves at none: the CDC-GS code's (3DGS's, with the opacity
    # learning rate of the current INRIA code and CDC-GS's geometric-mean initial scales).
    training_defaults: ClassVar[dict] = {
        "init_opacity": 0.1,
        "scale_rule": "cdc",
        "init_scale": 1.0,
        "opacity_lr": 0.025,
    }

    def __post_init__(self):
        super().__post_init__()
        target, cap = self.target_gaussians, self.max_gaussians
        if target is not None and cap is not None and target > cap:
            raise OptionError(
                f"--target-gaussians {self.target_gaussians} is above --max-gaussians {self.max_gaussians}"
            )
        if self.budget_max is not None and self.budget_schedule != "dash":
            raise OptionError("--budget-max is the bound of --budget-schedule dash: pass that too, or leave it out")
        if self.budget_schedule == "dash" and target is not None:
            raise OptionError(
                "--budget-schedule dash cannot be combined with --target-gaussians: the one caps growth at a budget "
                "that rises with the resolution, the other lands on a count (use --budget-max for the bound)"
            )

    def check(self, total_steps: int) -> None:
        last = self.last_densification()
        if self.target_gaussians is not None and (last is None or last > total_steps):
            where = "no iteration densifies" if last is None else f"the last densification step, {last}, is after"
            raise OptionError(
                f"--target-gaussians needs a densification step to land on, but {where} the run's "
                f"{total_steps} iterations (see --densify-until, --iters)"
            )

    @property
    def complexity_maps_method(self) -> str | None:
        return None

    def initialize_state(self, model: GaussianModel) -> dict:
        n, device = model.num, model.device
        state = {
            "grad_sum": torch.zeros(n, device=device, dtype=torch.float32),  # float32: the statistics kernel's
            "count": torch.zeros(n, device=device, dtype=torch.float32),
            "max_radius": torch.zeros(n, device=device, dtype=torch.float32),
        }
        if self.budget_schedule == "dash":
            # Kept across densification steps (:meth:`apply`): the count the run started with and
            # the momentum of the estimated bound (-1: the bound is preset).
            state["budget_initial"] = n
            state["budget_momentum"] = DASH_MOMENTUM_START * n if self.budget_max is None else -1
        return state

    # --- hooks -------------------------------------------------------------------------------

    def before_backward(self, ctx: StepContext, state: dict) -> None:
        if self.accumulates_at(ctx.step):
            if self.absgrad:
                ctx.info.retain_absgrad()
            else:
                ctx.info.means2d.retain_grad()

    def statistics(self) -> dict:
        return {"grad_sum": "sum", "count": "sum", "max_radius": "max"}

    def observe(self, ctx: StepContext, state: dict) -> None:
        if self.accumulates_at(ctx.step):
            self.accumulate(ctx, state)

    def refine(self, ctx: StepContext, state: dict) -> dict:
        log = {}
        if self.densifies_at(ctx.step):
            log.update(self.densify_and_prune(ctx, state))
        if self.resets_at(ctx.step):
            ops.reset_opacity(ctx.model, ctx.optimizer, self.reset_value)
            log["opacity_reset"] = 1
        return log

    def regularizer(self, ctx: StepContext) -> torch.Tensor | None:
        return None

    def refines_at(self, step: int) -> bool:
        return self.densifies_at(step) or self.resets_at(step)

    def after_step(self, ctx: StepContext, state: dict) -> None:
        pass

    def graph_signature(self, step: int):
        """What a captured step (``--cuda-graph``) of iteration ``step`` depends on in this
        strategy's hooks: steps with equal signatures replay one graph. Here, whether the step adds
        to the densification statistics (its hooks do nothing else, and nothing random); None
        would mean "take this step one operation at a time"."""
        return self.accumulates_at(step)

    # --- the schedule (iterations from 1; every test strict, as in the INRIA code) --------------

    def accumulates_at(self, step: int) -> bool:
        """Whether iteration ``step`` adds to the gradient statistics."""
        return step < self.densify_until

    def densifies_at(self, step: int) -> bool:
        """Whether iteration ``step`` densifies and prunes (600, 700, ..., 14900 by default)."""
        return self.densify_from < step < self.densify_until and step % self.densify_every == 0

    def resets_at(self, step: int) -> bool:
        """Whether iteration ``step`` resets the opacities (3000, 6000, 9000, 12000 by default)."""
        return step < self.densify_until and step % self.reset_every == 0

    # --- pieces (CDC-GS builds on these) ------------------------------------------------------

    def accumulate(self, ctx: StepContext, state: dict) -> None:
        """Add this view's positional gradient norm and screen radius of every visible Gaussian
        (one launch: :meth:`cdcgs.render.RasterizeInfo.accumulate_statistics`)."""
        ctx.info.accumulate_statistics(
            state["grad_sum"], state["count"], state["max_radius"], absolute=self.absgrad, halt=ctx.halt
        )

    def mean_gradient(self, state: dict) -> torch.Tensor:
        return torch.where(
            state["count"] > 0, state["grad_sum"] / state["count"].clamp_min(1), torch.zeros_like(state["grad_sum"])
        )

    def last_densification(self) -> int | None:
        """The last iteration that densifies (14900 by default), or None when none does."""
        last = self.densify_until - 1
        last -= last % self.densify_every
        return last if last > self.densify_from else None

    def growth_cap(self, ctx: StepContext, state: dict) -> tuple[int | None, str]:
        """(cap, rule) of growth at ``ctx.step``: ``target_gaussians`` fills up to it, else
        ``max_gaussians`` by ``cap_rule``, or the budget (:meth:`budget`) filled where that is lower."""
        if self.target_gaussians is not None:  # never above max_gaussians (__post_init__)
            return self.target_gaussians, "fill"
        if self.budget_schedule == "dash":
            budget = self.budget(ctx, state)
            if self.max_gaussians is None or budget < self.max_gaussians:
                return budget, "fill"
        return self.max_gaussians, self.cap_rule

    def budget_bound(self, state: dict) -> int:
        """The count the budget rises to: ``budget_max``, else the initial count plus the momentum."""
        if self.budget_max is not None:
            return self.budget_max
        return state["budget_initial"] + state["budget_momentum"]

    def budget(self, ctx: StepContext, state: dict) -> int:
        """DashGaussian's budget for the densification step ``ctx.step``, at the downscale
        ``ctx.resolution_scale`` (:func:`cdcgs.train.schedules.dash_budget`)."""
        if ctx.resolution_scale is None:
            raise OptionError(
                "--budget-schedule dash follows the training resolution: it needs --resolution-schedule dash"
            )
        return dash_budget(
            ctx.step,
            ctx.resolution_scale,
            ctx.model.num,
            state["budget_initial"],
            self.budget_bound(state),
            self.densify_until,
            self.densify_every,
        )

    def grow_masks(self, ctx: StepContext, state: dict, selected: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Split ``selected`` [N] into (clone, split) by size, under the cap (:meth:`growth_cap`).
        Under the budget with no ``budget_max``, the momentum then takes in the count selected (the
        growth the densification wanted), as DashGaussian's does after each densification step."""
        model = ctx.model
        small = model.scales().max(dim=-1).values <= self.clone_max_scale * ctx.extent
        clone, split = selected & small, selected & ~small
        cap, rule = self.growth_cap(ctx, state)
        if self.budget_schedule == "dash" and self.budget_max is None:
            state["budget_momentum"] = dash_momentum(state["budget_momentum"], int(selected.sum()))
        if cap is not None and rule == "skip" and model.num >= cap:
            return torch.zeros_like(clone), torch.zeros_like(split)
        if cap is not None and rule == "fill":
            room = cap - model.num
            growth = clone.sum() + (self.split_count - 1) * split.sum()
            if growth > room:
                # Keep the strongest candidates that fit.
                if room <= 0:
                    return torch.zeros_like(clone), torch.zeros_like(split)
                score = self.mean_gradient(state)
                cost = torch.where(split, float(self.split_count - 1), 1.0) * selected
                order = torch.argsort(torch.where(selected, score, torch.full_like(score, -1.0)), descending=True)
                fits = torch.zeros_like(selected)
                fits[order] = torch.cumsum(cost[order], 0) <= room
                clone, split = clone & fits, split & fits
        return clone, split

    def prune_mask(self, ctx: StepContext, max_radius: torch.Tensor) -> torch.Tensor:
        """Opacity below ``prune_opacity``; after the first reset also too large on screen or in the world."""
        model = ctx.model
        prune = model.opacities() < self.prune_opacity
        if ctx.step > self.reset_every:
            if self.prune_screen_size > 0:
                prune |= max_radius > self.prune_screen_size
            prune |= model.scales().max(dim=-1).values > self.prune_world_size * ctx.extent
        return prune

    def apply(
        self,
        ctx: StepContext,
        state: dict,
        clone: torch.Tensor,
        split: torch.Tensor,
        prune_extra: torch.Tensor | None = None,
        prune_after: Callable[[GaussianModel], torch.Tensor] | None = None,
    ) -> dict:
        """Clone, split, then prune by the rule, plus ``prune_extra`` [N] over the Gaussians before
        growth and ``prune_after(model)`` over those after it (newborns included); put the Gaussians
        in ``gaussian_order``; reset the statistics. New Gaussians are judged like 3DGS judges them:
        by their opacity and world size, with no screen size yet. At the last densification step
        ``target_gaussians`` is landed on (:meth:`land_on_target`)."""
        model, optimizer = ctx.model, ctx.optimizer
        score = self.mean_gradient(state)  # of the Gaussians before growth, for landing on the target
        grown = clone | split
        n_old, n_clone, n_split = model.num, int(clone.sum()), int(split.sum())
        ops.clone(model, optimizer, clone)  # [old, clones]
        split_mask = torch.cat([split, split.new_zeros(n_clone)])
        ops.split(
            model,
            optimizer,
            split_mask,
            count=self.split_count,
            scale_divisor=self.split_scale_divisor,
            generator=ctx.generator,
        )
        # Now [old without the split parents, clones, children].
        kept = ~split
        n_new = model.num - (n_old - n_split)
        max_radius = torch.cat([state["max_radius"][kept], state["max_radius"].new_zeros(n_new)])
        prune = self.prune_mask(ctx, max_radius)
        if prune_extra is not None:
            prune |= torch.cat([prune_extra[kept], prune_extra.new_zeros(n_new)])
        if prune_after is not None:
            prune |= prune_after(model)
        n_prune = int(prune.sum())
        # Each survivor's mean gradient before this step; -1 for the newborns and the grown.
        after = torch.cat([torch.where(grown[kept], -1.0, score[kept]), score.new_full((n_new,), -1.0)])[~prune]
        ops.remove(model, optimizer, prune)
        log = {"cloned": n_clone, "split": n_split, "pruned": n_prune}
        if self.target_gaussians is not None and ctx.step == self.last_densification():
            log.update(self.land_on_target(ctx, after))
        # On --dist-mode shards (a whole scene to decide over) this process's slice alone: no faster
        # there on 2 x H200 (docs/distributed.md), so auto keeps the appended order.
        if self.gaussian_order == "morton" or (self.gaussian_order == "auto" and ctx.whole_scene is None):
            ops.reorder(model, optimizer, ops.morton_order(model.params["means"]))
        kept_state = {key: state[key] for key in ("budget_initial", "budget_momentum") if key in state}
        state.update(self.initialize_state(model))  # the statistics start again: nothing to reorder
        state.update(kept_state)  # the budget's, which lasts the run
        if self.budget_schedule == "dash":
            log["budget_bound"] = self.budget_bound(state)
        return {**log, "gaussians": model.num}

    def land_on_target(self, ctx: StepContext, score: torch.Tensor) -> dict:
        """Make the count exactly ``target_gaussians``: clone (3DGS's clone) the Gaussians of
        highest ``score`` [N] (the mean gradient; -1 for those grown or born this step, so they
        come last), or remove the least opaque. Cloning at most doubles the count: a target
        further away is logged as ``target_short``."""
        model, target = ctx.model, self.target_gaussians
        if model.num < target:
            top = torch.argsort(score, descending=True, stable=True)[: target - model.num]
            mask = torch.zeros(model.num, dtype=torch.bool, device=model.device)
            mask[top] = True
            count = int(mask.sum())
            ops.clone(model, optimizer=ctx.optimizer, mask=mask)
            log = {"target_cloned": count}
            if model.num < target:
                log["target_short"] = target - model.num
            return log
        if model.num > target:
            order = torch.argsort(model.opacities().detach(), stable=True)[: model.num - target]
            mask = torch.zeros(model.num, dtype=torch.bool, device=model.device)
            mask[order] = True
            ops.remove(model, ctx.optimizer, mask)
            return {"target_pruned": int(mask.sum())}
        return {}

    def densify_and_prune(self, ctx: StepContext, state: dict) -> dict:
        selected = self.mean_gradient(state) >= self.grad_threshold
        clone, split = self.grow_masks(ctx, state, selected)
        return self.apply(ctx, state, clone, split)
