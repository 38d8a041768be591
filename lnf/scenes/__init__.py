"""Scenes: bodies with a Lagrangian and a full-order simulator for ground truth."""
from lnf.scenes.base import DiscretePotential, GeneralizedForce, ModalKinetic, Scene, StabilityCases
from lnf.scenes.bump import BumpPendulum
from lnf.scenes.double_pendulum import LiftedDoublePendulum
from lnf.scenes.elastic import ElasticCantilever
from lnf.scenes.pendulum import LiftedPendulum
from lnf.scenes.soft_body import SoftBody

SCENES: dict[str, type[Scene]] = {"pendulum": LiftedPendulum, "double_pendulum": LiftedDoublePendulum,
                                  "bump": BumpPendulum, "elastic": ElasticCantilever, "soft_body": SoftBody}

__all__ = ["DiscretePotential", "GeneralizedForce", "ModalKinetic", "Scene", "StabilityCases", "LiftedPendulum",
           "LiftedDoublePendulum", "BumpPendulum", "ElasticCantilever", "SoftBody", "SCENES"]
