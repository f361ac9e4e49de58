"""warpcontact: a differentiable rigid-body contact model with long-range influence, on NVIDIA Warp.

Implements the separating-plane contact potential with a global 1/x barrier, its closed-form
centred limit and quintic blending (Ye, Wu, Komura, Pan: "Efficient Differentiable Contact
Model with Long-range Influence"). See docs/architecture.md for the pipeline.
"""

from .leaf import (
    LeafStatus,
    TrianglePairPotential,
    centered_potential,
    quintic_blend,
    triangle_pair_potential,
)

__version__ = "0.1.0"

__all__ = [
    "LeafStatus",
    "TrianglePairPotential",
    "centered_potential",
    "quintic_blend",
    "triangle_pair_potential",
]
