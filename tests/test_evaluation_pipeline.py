"""lnf/evaluation_pipeline.py: what every evaluation route is given."""
from types import SimpleNamespace

import numpy as np

from lnf.evaluation import reduction_subset
from lnf.evaluation_pipeline import EvaluationData
from lnf.quadrature import uniform_grid

BOUNDS = [[-1.0, 1.0], [-1.0, 1.0]]


class _Split(SimpleNamespace):
    """Two stored trajectories of five frames on `points`."""

    def __init__(self, points: np.ndarray) -> None:
        fields = np.zeros((2, 5, len(points), 1), dtype=np.float32)
        super().__init__(states=np.zeros((2, 5, 2)), times=0.05 * np.arange(5), train_times=3, fine_points=points,
                         fields=fields, velocities=fields, controls=None, weights=None)

    def __len__(self) -> int:
        return self.states.shape[0]

    def energy_parts(self, scene):
        return None


def test_the_true_fields_are_reduced_on_the_fine_grids_own_sub_grid_whoever_evaluates():
    """Without a grid shape a flat stride through a 64² grid keeps every 4th column; of_split finds the grid, so ρ̃
    reads the same evenly strided 32² sub-grid from the training callback, lnf.evaluate and the studies."""
    scene = SimpleNamespace(bounds=BOUNDS)
    grid = uniform_grid(64, BOUNDS).points.numpy()
    data = EvaluationData.of_split(_Split(grid), scene)
    assert data.grid_shape == (64, 64)
    sub = reduction_subset(len(grid), data.grid_shape, 1024)
    assert len(np.unique(grid[sub][:, 0])) == len(np.unique(grid[sub][:, 1])) == 32  # every 2nd point on each axis
    flat = reduction_subset(len(grid), None, 1024)
    assert sorted(len(np.unique(grid[flat][:, k])) for k in (0, 1)) == [16, 64]  # a flat stride: every 4th column
    scattered = np.random.default_rng(0).uniform(-1, 1, (4096, 2))
    assert EvaluationData.of_split(_Split(scattered), scene).grid_shape is None
    subset = np.arange(0, 4096, 3)
    assert EvaluationData.of_split(_Split(grid), scene, subset=subset).grid_shape is None
