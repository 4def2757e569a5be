"""Mode decoupling of a mirror-stacked gauge pair (the paper's equations for r̂ and ε̂_s).

Under Kirchhoff–Love kinematics the layer at offset h from the neutral plane has strain
ε = (1 + ε_s)(1 + h/r) − 1 with r the signed bend radius (r > 0 convex: upper layer in tension).
For a gauge of rest length g whose neutral-plane arc has length L and normal turning angle
Θ = ∫κ_n ds, averaging over the gauge gives exactly

    ε_u = L/g − 1 + h_u Θ/g,        ε_l = L/g − 1 − h_l Θ/g,

so the two estimates below are the gauge-averaged curvature κ̂ = Θ/L and stretch ε̂_s = L/g − 1,
with no circular-arc assumption.
"""
from __future__ import annotations

import numpy as np

__all__ = ["decouple"]


def _check_offsets(h_upper: float, h_lower: float) -> tuple[float, float]:
    h_u, h_l = float(h_upper), float(h_lower)
    if not (np.isfinite(h_u) and np.isfinite(h_l)) or h_u < 0 or h_l < 0 or h_u + h_l <= 0:
        raise ValueError(
            f"layer offsets must be finite, >= 0 and not both zero; got h_upper={h_upper!r}, "
            f"h_lower={h_lower!r}"
        )
    return h_u, h_l


def decouple(
    eps_upper: np.ndarray,
    eps_lower: np.ndarray,
    h_upper: float = 0.2,
    h_lower: float = 0.2,
) -> tuple[np.ndarray, np.ndarray]:
    """Curvature and stretch of every sensing unit from its upper/lower layer strains.

    Parameters
    ----------
    eps_upper, eps_lower : arrays of the same shape, engineering strain (0.01 = 1 %).
    h_upper, h_lower : distances (mm) of the upper and lower gauge from the neutral plane.

    Returns
    -------
    kappa : signed curvature 1/r̂ (1/mm), r̂ = ((1+ε_l)h_u + (1+ε_u)h_l)/(ε_u − ε_l);
        positive is convex (upper layer in tension); exactly 0 on a flat unit.
    eps_s : stretch ε̂_s = (ε_u h_l + ε_l h_u)/(h_u + h_l) of the neutral plane.

    The curvature is computed as 1/r̂, whose denominator (h_u + h_l)(1 + ε̂_s) only vanishes for
    a layer compressed to zero length; such units, and NaN inputs, give NaN.
    """
    eu = np.asarray(eps_upper, dtype=float)
    el = np.asarray(eps_lower, dtype=float)
    if eu.shape != el.shape:
        raise ValueError(f"eps_upper and eps_lower must have the same shape, got {eu.shape} and {el.shape}")
    h_u, h_l = _check_offsets(h_upper, h_lower)
    denom = (1.0 + el) * h_u + (1.0 + eu) * h_l
    valid = denom > 0  # False for NaN too
    kappa = np.full(eu.shape, np.nan)
    np.divide(eu - el, denom, out=kappa, where=valid)
    eps_s = (eu * h_l + el * h_u) / (h_u + h_l)
    return kappa, eps_s
