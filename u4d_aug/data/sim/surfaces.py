"""Measured surface model (`lidar.surface_model: measured`): per-material remission gain and range scatter.

Fitted to the labelled real SemanticKITTI seq-00 frames 0-2 (../shared/data/real/SOURCES.md) with `u4d sim-report`
together with the measured sensor terms of configs/sim/varied.yaml (per-laser gain, speckle, range noise, the
incidence and range falloff): `gain` scales a material's reflectivity so that its class's remission histogram within
50 m meets the real one, `penetration` (mean extra range, m, exponential) sets the range roughness of porous and
uneven surfaces (real median |second difference| of range along a ring: vegetation 47 mm, terrain 57 mm, road 14 mm).
Materials not listed keep gain 1 and their own penetration (geometry.MATERIALS). The basic model (the default world)
uses neither.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from u4d_aug.data.sim.geometry import MATERIALS


@dataclass(frozen=True)
class SurfaceFit:
    """One material's measured terms; None keeps the material's own value (geometry.MATERIALS) or `lidar.speckle`."""

    gain: float = 1.0  # remission gain
    speckle: float | None = None  # std of the log remission per return
    zero_prob: float | None = None  # returns that read 0
    penetration: float | None = None  # m, mean extra range (exponential)


MEASURED: dict[str, SurfaceFit] = {
    "asphalt": SurfaceFit(gain=1.05, speckle=0.10, zero_prob=0.15),
    "parking": SurfaceFit(gain=1.00),
    "paint": SurfaceFit(gain=0.60, speckle=0.60),
    "paving": SurfaceFit(gain=0.95),
    "curb": SurfaceFit(gain=0.95),
    "facade": SurfaceFit(gain=0.95, speckle=0.05, zero_prob=0.00),
    "glass": SurfaceFit(gain=1.50, speckle=0.30),
    "leaves": SurfaceFit(gain=0.75, zero_prob=0.08, penetration=0.06),
    "hedge": SurfaceFit(gain=1.00, speckle=0.15, penetration=0.05),
    "bark": SurfaceFit(gain=0.95, speckle=0.25, zero_prob=0.06),
    "grass": SurfaceFit(gain=0.90, speckle=0.10, zero_prob=0.04, penetration=0.03),
    "car_paint": SurfaceFit(gain=1.30, speckle=0.35, zero_prob=0.08),
    "car_glass": SurfaceFit(gain=0.60, speckle=0.45),
    "tire": SurfaceFit(gain=0.60, speckle=0.05),
    "metal": SurfaceFit(gain=1.20, speckle=0.25, zero_prob=0.15),
    "sign": SurfaceFit(gain=1.10, speckle=0.40),
    "fence": SurfaceFit(gain=1.35, speckle=0.10),
    "plastic": SurfaceFit(gain=1.00),
}


@dataclass
class MaterialTerms:
    """Per material index: remission gain, speckle, zero probability, penetration (float32 arrays)."""

    gain: np.ndarray
    speckle: np.ndarray
    zero_prob: np.ndarray
    penetration: np.ndarray


def material_terms(model: str, speckle: float = 0.0) -> MaterialTerms:
    """Terms of surface model 'basic' (the materials as they are, `speckle` for all) or 'measured' (MEASURED)."""
    terms = MaterialTerms(
        gain=np.ones(len(MATERIALS), dtype=np.float32),
        speckle=np.full(len(MATERIALS), speckle, dtype=np.float32),
        zero_prob=np.array([m.zero_prob for m in MATERIALS], dtype=np.float32),
        penetration=np.array([m.penetration for m in MATERIALS], dtype=np.float32),
    )
    if model == "basic":
        return terms
    elif model == "measured":
        for k, material in enumerate(MATERIALS):
            fit = MEASURED.get(material.name, SurfaceFit())
            terms.gain[k] = fit.gain
            for name in ("speckle", "zero_prob", "penetration"):
                if getattr(fit, name) is not None:
                    getattr(terms, name)[k] = getattr(fit, name)
        return terms
    raise ValueError(f"surface model {model!r}: expected 'basic' or 'measured'")
