"""Named strategy presets: every row of the CDC-GS paper's variants table as options of
:class:`cdcgs.train.cdc.CDC`, or of :class:`cdcgs.train.mcmc.MCMC` for the 3DGS-MCMC rows.

Plain data, so that the configuration and the command line can list the names without importing
any kernel. ``3dgs`` is the baseline: 3DGS's adaptive density control as the 3DGS code runs it,
through the same class with every CDC-GS part off, so that ``--log-correlation`` measures Γ exactly
as the CDC-GS presets do (every view at every densification step, the same w_max). The CDC-GS and
3DGS presets train with the CDC-GS code's learning rates and initial scales, the MCMC presets with
the 3DGS-MCMC code's (the strategies' ``training_defaults``).
"""

from __future__ import annotations

import dataclasses

from ..errors import OptionError

__all__ = [
    "ALIASES",
    "PRESETS",
    "PRESET_CLASS",
    "PRESET_TRAINING",
    "TRAINING_DEFAULTS",
    "build_preset",
    "canonical_name",
]

_BASELINE = {
    "cdc_densify": False,
    "cdc_prune": False,
    "caat": False,
    "periodic_prune": False,
    "log_correlation": False,
}
_MCMC = {"cdc_densify": False, "cdc_prune": False, "log_correlation": False, "target_gaussians": 1_000_000}

PRESETS: dict[str, dict] = {
    "3dgs": dict(_BASELINE),
    "absgs": {**_BASELINE, "absgrad": True, "grad_threshold": 8e-4},
    "cdc": {},
    "cdc-hq": {"rho_densify": 0.02},
    "caat-only": {"cdc_densify": False, "cdc_prune": False, "periodic_prune": False},
    "cdc-only": {"caat": False},
    "cdc-prune-only": {"cdc_densify": False, "caat": False},
    "cdc-reverse": {"reverse": True},
    "cdc-compact": {"centre": "quantile", "rho_prune": 0.5},
    "mcmc": dict(_MCMC),
    "mcmc-cdc": {**_MCMC, "cdc_densify": True, "cdc_prune": True, "log_correlation": True},
    "fast": {**_BASELINE, "budget_schedule": "dash"},
}

# Training options (not the strategy's) that a preset sets where the run leaves them at none.
# ``fast``: the speed features of issue 21 together, 3DGS's densification under DashGaussian's
# resolution schedule and primitive budget, with Taming 3DGS's selective Adam. None of the three
# is exact; docs/benchmarks.md has what each costs and saves.
PRESET_TRAINING: dict[str, dict] = {"fast": {"optimizer": "selective", "resolution_schedule": "dash"}}

# The training options' values where neither the run, its preset nor its strategy sets them.
TRAINING_DEFAULTS: dict = {"optimizer": "adam", "resolution_schedule": "none"}

# The strategy class of each preset that is not CDC (cdcgs.train.strategies.STRATEGY_CLASSES).
PRESET_CLASS: dict[str, str] = {"mcmc": "MCMC", "mcmc-cdc": "MCMC"}

# Names that earlier versions wrote into run folders: `adc` ran the same rules as `3dgs`.
ALIASES: dict[str, str] = {"adc": "3dgs"}


def canonical_name(name: str) -> str:
    """The preset that ``name`` (a preset or an alias) stands for.

    Raises:
        ValueError: no preset has this name.
    """
    name = ALIASES.get(name, name)
    if name not in PRESETS:
        raise OptionError(f"unknown strategy {name!r}; known: {', '.join(PRESETS)}")
    return name


def build_preset(cls: type, name: str, options: dict | None = None):
    """Strategy class ``cls`` with preset ``name``'s values, overridden by ``options``.

    Raises:
        OptionError: an unknown preset, a preset of another class, an option ``cls`` does not
            have, or a value it refuses.
    """
    name = canonical_name(name)
    if PRESET_CLASS.get(name, "CDC") != cls.__name__:
        raise OptionError(f"strategy {name!r} is not a {cls.__name__} preset")
    options = dict(options or {})
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise OptionError(f"strategy {name!r} has no option(s) {unknown}; it has {sorted(known)}")
    return cls(**{**PRESETS[name], **options})
