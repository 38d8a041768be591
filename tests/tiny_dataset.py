"""The tiny lifted-pendulum dataset the dataset tests share: its settings and its fixtures (import them)."""
from __future__ import annotations

from pathlib import Path

import pytest

from lnf.dataset import DatasetConfig, generate_dataset
from lnf.scenes import LiftedPendulum

CFG = DatasetConfig(n_train=3, n_val=1, n_test=2, n_times=12, dt=0.05, train_times=6, fine_resolution=8,
                    coarse_resolution=8, observed_fraction=0.25, seed=0)


@pytest.fixture(scope="module")
def scene() -> LiftedPendulum:
    return LiftedPendulum()


@pytest.fixture(scope="module")
def shared_file(tmp_path_factory, scene) -> Path:
    """One generated file per test module, never modified."""
    return generate_dataset(scene, CFG, tmp_path_factory.mktemp("data") / "pendulum.h5")


@pytest.fixture
def fresh_file(tmp_path, shared_file) -> Path:
    """A private copy of the generated file, for tests that damage or modify it."""
    dst = tmp_path / "pendulum.h5"
    dst.write_bytes(shared_file.read_bytes())
    return dst
