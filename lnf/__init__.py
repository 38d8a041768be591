"""lnf — Lagrangian neural fields: structure-preserving, discretization-agnostic reduced-order models
of continuum mechanics (modulated SIREN embedding, K-step reduction, pulled-back Lagrangian dynamics).

    model = lnf.load("outputs/pendulum/runs/<date>/checkpoints/last.ckpt")
"""
from lnf.integrators import RK4, Dopri5, ImplicitMidpoint, RolloutDivergedError, get_integrator
from lnf.model import LagrangianNeuralField, build, load
from lnf.quadrature import GaussLegendre, GivenPoints, Quadrature, UniformGrid, midpoint_grid
from lnf.scenes import LiftedPendulum, Scene

__version__ = "0.1.0"

__all__ = ["load", "build", "LagrangianNeuralField", "LiftedPendulum", "Scene", "Quadrature", "GaussLegendre",
           "UniformGrid", "GivenPoints", "midpoint_grid", "RK4", "ImplicitMidpoint", "Dopri5", "get_integrator",
           "RolloutDivergedError", "__version__"]
