import os

import numpy as np
import pytest
import torch

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")
# Figures as PNG alone (a vector PDF beside each costs about a second per figure, in every training run of the
# suite); the tests that check the PDF set LNF_FIGURE_PDF=1 themselves.
os.environ.setdefault("LNF_FIGURE_PDF", "0")
# The suite runs in pytest-xdist workers (pyproject's addopts): share the cores among them, here and in the
# subprocesses the end-to-end tests start, instead of each worker's torch spinning threads on every core.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
_THREADS = max(1, min(2, (os.cpu_count() or 1) // _WORKERS))
os.environ.setdefault("OMP_NUM_THREADS", str(_THREADS))
torch.set_num_threads(_THREADS)
# and an expensive reference's dataset is simulated in the test's own process, not in a pool beside the workers
# (tests/test_dataset_parallel.py sets it for its own cases)
os.environ.setdefault("LNF_SIMULATION_WORKERS", "1")


@pytest.fixture
def pendulum():
    from lnf.scenes import LiftedPendulum

    return LiftedPendulum()


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def pytest_collection_modifyitems(config, items):
    """The benchmark-study smoke tests (a minute or two each) first, the rest in file order after them: the two
    pytest-xdist workers then finish together instead of one waiting on a long test that started last. Every
    test is independent of the others, so the order changes only the wall-clock time."""
    items.sort(key=lambda item: 0 if item.nodeid.startswith("tests/test_experiments.py") else 1)
