"""What `clothd tune` searches: the tracker's mass–spring constants, within the bounds clothd/config declares.

The bounds are read from PhysicsConfig's Field metadata, so the search can never propose a value the
configuration would refuse. Where a bound is open at zero (gt=0, ge=0) the search stops FLOOR_DECADES
below the upper bound instead: a log scale cannot reach zero, and no fabric needs less. Constants whose
range spans decades are searched on a log scale, so that CMA-ES steps by ratios, as a fabric differs.

slack_strain must stay below strain_limit (PhysicsConfig's own rule); it is searched as its share of the
limit, so every point of the box is a valid configuration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import annotated_types
import optuna

from clothd.config import PhysicsConfig

# A bound open at zero becomes this many decades below the upper bound.
FLOOR_DECADES = 5.0
SLACK_SHARE = "slack_share"  # slack_strain / strain_limit


@dataclass(frozen=True)
class Dimension:
    name: str  # a PhysicsConfig field, or SLACK_SHARE
    low: float
    high: float
    log: bool


def _bounds(field: str) -> tuple[float, float]:
    """(low, high) of a PhysicsConfig field from its gt/ge/lt/le metadata, an open zero floored.

    An open bound (gt, lt) is searched from the next float inside it: the sampler clips its proposals
    onto the box's edges, and an edge the configuration refuses would end the worker."""
    low, high = -math.inf, math.inf
    for m in PhysicsConfig.model_fields[field].metadata:
        if isinstance(m, annotated_types.Gt):
            low = math.nextafter(float(m.gt), math.inf)  # type: ignore[arg-type]
        elif isinstance(m, annotated_types.Ge):
            low = float(m.ge)  # type: ignore[arg-type]
        elif isinstance(m, annotated_types.Lt):
            high = math.nextafter(float(m.lt), -math.inf)  # type: ignore[arg-type]
        elif isinstance(m, annotated_types.Le):
            high = float(m.le)  # type: ignore[arg-type]
    if not math.isfinite(low) or not math.isfinite(high):
        raise ValueError(f"physics.{field} declares no bounds to search within")
    if low <= math.ulp(0.0):  # ge=0 or gt=0
        low = high * 10.0**-FLOOR_DECADES
    return low, high


def _dimension(field: str, log: bool) -> Dimension:
    low, high = _bounds(field)
    return Dimension(field, low, high, log)


# The constants that shape the cloth's motion. stick_speed_m_s and substeps are numerics, not fabric;
# compression_k_ratio is how the model buckles, which the tracker's fold heights rely on.
SPACE: tuple[Dimension, ...] = (
    _dimension("areal_density_kg_m2", log=True),
    _dimension("stretch_k_n_m", log=True),
    _dimension("shear_k_n_m", log=True),
    _dimension("flexion_k_n_m", log=True),
    _dimension("damping_1_s", log=True),
    _dimension("friction_mu", log=True),
    _dimension("strain_limit", log=True),
    # Half-open [0, 1): the share stops just short of the limit itself.
    Dimension(SLACK_SHARE, 0.0, 0.95, log=False),
)
TUNED_FIELDS = (*(d.name for d in SPACE if d.name != SLACK_SHARE), "slack_strain")


def suggest(trial: optuna.Trial) -> dict[str, float]:
    """One point of the search space, as the trial's parameters."""
    return {d.name: trial.suggest_float(d.name, d.low, d.high, log=d.log) for d in SPACE}


def point_of(physics: PhysicsConfig) -> dict[str, float]:
    """The search-space point of a configuration (the start of a search, or a design to enqueue), clipped
    into the box."""
    values: dict[str, Any] = physics.model_dump()
    values[SLACK_SHARE] = physics.slack_strain / physics.strain_limit
    return {d.name: min(max(float(values[d.name]), d.low), d.high) for d in SPACE}


def physics_of(params: dict[str, float], base: PhysicsConfig) -> PhysicsConfig:
    """base with the point's constants laid over it (validated again)."""
    values = {k: v for k, v in params.items() if k != SLACK_SHARE}
    values["slack_strain"] = params[SLACK_SHARE] * params["strain_limit"]
    return PhysicsConfig.model_validate(base.model_dump() | values)


def physics_fields(physics: PhysicsConfig) -> dict[str, float]:
    """The tuned fields of a configuration, in config.yaml's names (best.yaml, the table)."""
    dumped = physics.model_dump()
    return {name: float(dumped[name]) for name in TUNED_FIELDS}
