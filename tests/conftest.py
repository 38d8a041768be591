import os

import numpy as np
import pytest
import torch

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")
torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture
def pendulum():
    from lnf.scenes import LiftedPendulum

    return LiftedPendulum()


@pytest.fixture
def rng():
    return np.random.default_rng(0)
