"""xmetro_ros.sim: the virtual laser line scanner (ray casting on the organized grid + named physical effects).

Public API: ``simulate_scan``, ``EFFECTS`` (name → effect class, in application order), ``UnknownEffectError``,
``EffectConfigError``; the study campaign lives in ``xmetro_ros.sim.campaign``. See docs/simulator.md.

May import: scan.
"""

from .effect import Effect, EffectConfigError, SimContext, UnknownEffectError
from .effects import EFFECTS, effects_table, resolve_effects
from .scanner_sim import simulate_scan

__all__ = [
    "EFFECTS",
    "Effect",
    "EffectConfigError",
    "SimContext",
    "UnknownEffectError",
    "effects_table",
    "resolve_effects",
    "simulate_scan",
]
