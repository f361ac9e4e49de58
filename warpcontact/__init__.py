"""warpcontact: a differentiable rigid-body contact model with long-range influence, on NVIDIA Warp.

Implements the separating-plane contact potential with a global 1/x barrier, its closed-form
centred limit and quintic blending (Ye, Wu, Komura, Pan: "Efficient Differentiable Contact
Model with Long-range Influence"). See docs/architecture.md for the pipeline.
"""

from . import _guarded_imports  # noqa: F401  (first: its docstring says why)
from .builder import ModelBuilder
from .contact import CENTRED_WEIGHTS, CONTACT_MODES, ContactEvaluation, ContactModel, TermLists
from .leaf import (
    LEAF_PRECISIONS,
    LeafStatus,
    TrianglePairPotential,
    centered_potential,
    quintic_blend,
    triangle_pair_potential,
)

from .solver import ImplicitSolver, SolverError, StepInfo
from .sphere_tree import SphereTree, build_sphere_tree
from .types import Control, Model, State, set_body_velocity

__version__ = "0.1.0"

__all__ = [
    "LEAF_PRECISIONS",
    "LeafStatus",
    "TrianglePairPotential",
    "centered_potential",
    "quintic_blend",
    "triangle_pair_potential",
    "CENTRED_WEIGHTS",
    "CONTACT_MODES",
    "ContactEvaluation",
    "ContactModel",
    "TermLists",
    "SphereTree",
    "build_sphere_tree",
    "Control",
    "ImplicitSolver",
    "Model",
    "ModelBuilder",
    "SolverError",
    "State",
    "StepInfo",
    "set_body_velocity",
]
