"""The strategy classes behind the presets, and the one place that builds a strategy by name."""

from __future__ import annotations

import dataclasses
import typing

from .cdc import CDC
from .mcmc import MCMC
from .presets import PRESET_CLASS, PRESETS, build_preset, canonical_name

__all__ = ["STRATEGY_CLASSES", "make_strategy", "strategy_class", "strategy_fields"]

STRATEGY_CLASSES = {"CDC": CDC, "MCMC": MCMC}


def strategy_class(name: str) -> type:
    """The class of preset ``name`` (aliases accepted)."""
    return STRATEGY_CLASSES[PRESET_CLASS.get(canonical_name(name), "CDC")]


def make_strategy(name: str, options: dict | None = None):
    """The named preset (:data:`cdcgs.train.presets.PRESETS`, aliases accepted) with ``options``
    overriding its hyperparameters.

    Raises:
        OptionError: an unknown preset or option name, or a value the strategy refuses.
    """
    return build_preset(strategy_class(name), name, options)


def strategy_fields() -> list[tuple[dataclasses.Field, type, list[str]]]:
    """Every strategy option once: (field, its type, the presets that have it), by name."""
    by_name: dict[str, tuple] = {}
    for cls in STRATEGY_CLASSES.values():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            by_name.setdefault(f.name, (f, hints[f.name]))
    result = []
    for name in sorted(by_name):
        f, hint = by_name[name]
        presets = [p for p in PRESETS if name in {g.name for g in dataclasses.fields(strategy_class(p))}]
        result.append((f, hint, presets))
    return result
