"""Named strategy presets: every row of the CDC-GS paper's variants table (except MCMC) as options
of :class:`cdcgs.train.cdc.CDC`.

Plain data, so that the configuration and the command line can list the names without importing
any kernel. ``3dgs`` is the baseline: 3DGS's adaptive density control as the 3DGS code runs it,
through the same class with every CDC-GS part off, so that ``--log-correlation`` measures Γ exactly
as the CDC-GS presets do.
"""

from __future__ import annotations

from ..errors import OptionError

__all__ = ["ALIASES", "PRESETS", "canonical_name"]

_BASELINE = {
    "cdc_densify": False,
    "cdc_prune": False,
    "caat": False,
    "periodic_prune": False,
    "log_correlation": False,
    "complexity_schedule": "online",
}

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
}

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
