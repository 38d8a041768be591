"""Baselines measured by the same pipeline as our model (docs/method.md §7.5): full-order, POD-Galerkin, black-box latent MLP;
and Operator Inference (through the `opinf` package, imported when first used), run by experiments/operator_inference.py."""
from lnf.baselines.full_order import FullOrderModel, NodalDynamics
from lnf.baselines.latent_mlp import LatentMLPDynamics, LearnedLatentDynamics, latent_trajectories
from lnf.baselines.operator_inference import OperatorInference
from lnf.baselines.pod import LegendreBasis, LinearEmbedding, PODGalerkin

__all__ = ["FullOrderModel", "NodalDynamics", "LatentMLPDynamics", "LearnedLatentDynamics", "latent_trajectories",
           "LegendreBasis", "LinearEmbedding", "PODGalerkin", "OperatorInference"]
