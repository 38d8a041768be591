"""Scenes: bodies with a Lagrangian and a full-order simulator for ground truth."""
from lnf.scenes.base import DiscretePotential, Scene
from lnf.scenes.pendulum import LiftedPendulum

SCENES: dict[str, type[Scene]] = {"pendulum": LiftedPendulum}

__all__ = ["DiscretePotential", "Scene", "LiftedPendulum", "SCENES"]
