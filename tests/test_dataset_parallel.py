"""An expensive reference's trajectories simulated by several processes: the same numbers as by one."""
import numpy as np
import pytest

import lnf.dataset as D
from lnf.scenes.elastic import ElasticCantilever


def _initial(scene, n):
    return scene.sample_initial_states(n, np.random.default_rng(0))


def test_worker_processes_simulate_the_same_trajectories_as_one_process(monkeypatch):
    scene = ElasticCantilever(mesh=(4, 2))
    initial, times = _initial(scene, 6), np.linspace(0.0, 0.2, 5)
    monkeypatch.setattr(D.generate, "SIMULATION_CHUNK", 2)  # three chunks
    monkeypatch.setenv(D.WORKERS_ENV, "1")
    serial = D._simulate(scene, initial, times, "train")
    monkeypatch.setenv(D.WORKERS_ENV, "2")
    parallel = D._simulate(scene, initial, times, "train")
    assert serial.shape[:2] == (6, 5) and np.array_equal(serial, parallel)


def test_chunks_are_shared_evenly_among_the_processes(monkeypatch):
    """8 trajectories on 2 processes: 2 × 4, not one chunk of 8 in one process; 20: 8, 8, 4 (at most the cap)."""
    monkeypatch.setenv(D.WORKERS_ENV, "2")
    assert D.simulation_chunks(8) == ([slice(0, 4), slice(4, 8)], 2)
    assert [s.stop - s.start for s in D.simulation_chunks(20)[0]] == [8, 8, 4]
    assert D.simulation_chunks(1) == ([slice(0, 1)], 1)
    monkeypatch.setenv(D.WORKERS_ENV, "1")
    assert D.simulation_chunks(8) == ([slice(0, 8)], 1)


def test_a_soft_body_simulated_in_other_chunks_gives_the_same_numbers(monkeypatch):
    """Neo-Hookean (a logarithm in its stress): 5 trajectories at once in one process, or as 3 + 2 in two."""
    from lnf.scenes.soft_body import SoftBody

    scene = SoftBody(cells=[2, 1, 1])
    initial, times = _initial(scene, 5), np.linspace(0.0, 0.05, 3)
    monkeypatch.setenv(D.WORKERS_ENV, "1")
    serial = D._simulate(scene, initial, times, "train")
    monkeypatch.setenv(D.WORKERS_ENV, "2")
    assert D.simulation_chunks(5)[0] == [slice(0, 3), slice(3, 5)]
    assert np.array_equal(D._simulate(scene, initial, times, "train"), serial)


def test_a_scene_of_ones_own_need_not_be_picklable(monkeypatch):
    """The workers are forked: they inherit the scene, nothing is pickled but the states."""
    scene = ElasticCantilever(mesh=(4, 2))
    scene.hook = lambda: None  # a lambda cannot be pickled
    initial, times = _initial(scene, 4), np.linspace(0.0, 0.1, 3)
    monkeypatch.setattr(D, "SIMULATION_CHUNK", 2)
    monkeypatch.setenv(D.WORKERS_ENV, "2")
    out = D._simulate(scene, initial, times, "train")
    assert out.shape[:2] == (4, 3) and np.isfinite(out).all()


@pytest.mark.parametrize("value", ["0", "two", "-1"])
def test_a_bad_worker_count_names_the_variable_and_the_value(monkeypatch, value):
    monkeypatch.setenv(D.WORKERS_ENV, value)
    with pytest.raises(D.DatasetError, match=rf"LNF_SIMULATION_WORKERS={value!r}.*whole number"):
        D.simulation_workers(4)


def test_the_worker_count_is_at_most_the_number_of_chunks(monkeypatch):
    monkeypatch.setenv(D.WORKERS_ENV, "8")
    assert D.simulation_workers(3) == 3
    monkeypatch.delenv(D.WORKERS_ENV)
    assert 1 <= D.simulation_workers(100) <= 100


# ---------------------------------------------------------------------------------------------------
# the ground truth lnf.evaluate simulates for new horizons or initial states, kept for the next job
# ---------------------------------------------------------------------------------------------------
def test_the_ground_truth_of_an_expensive_reference_is_simulated_once(tmp_path, monkeypatch):
    scene = ElasticCantilever(mesh=(4, 2))
    initial, times = _initial(scene, 2), np.linspace(0.0, 0.1, 3)
    first = D.simulated_ground_truth(scene, initial, times, tmp_path)
    assert len(list(tmp_path.glob("elastic-*.npy"))) == 1 and not list(tmp_path.glob("*.tmp-*"))

    def refuse(*_):
        raise AssertionError("simulated again")

    monkeypatch.setattr(scene, "simulate", refuse)
    assert np.array_equal(D.simulated_ground_truth(scene, initial, times, tmp_path), first)
    with pytest.raises(AssertionError, match="simulated again"):  # other initial states: another file
        D.simulated_ground_truth(scene, initial[::-1].copy(), times, tmp_path)
    with pytest.raises(AssertionError, match="simulated again"):  # another scene: another file
        monkeypatch.setattr(scene, "spec", lambda: {"other": 1})
        D.simulated_ground_truth(scene, initial, times, tmp_path)


def test_a_damaged_ground_truth_file_is_simulated_again_with_a_warning(tmp_path, caplog):
    scene = ElasticCantilever(mesh=(4, 2))
    initial, times = _initial(scene, 2), np.linspace(0.0, 0.1, 3)
    first = D.simulated_ground_truth(scene, initial, times, tmp_path)
    (path,) = tmp_path.glob("elastic-*.npy")
    path.write_bytes(path.read_bytes()[:100])  # truncated
    with caplog.at_level("WARNING", logger="lnf.dataset"):
        again = D.simulated_ground_truth(scene, initial, times, tmp_path)
    assert np.array_equal(again, first) and str(path) in caplog.text and "again" in caplog.text
    assert np.array_equal(np.load(path), first)  # replaced by a whole file


def test_a_cheap_reference_is_not_cached(tmp_path):
    class Cheap:
        expensive_reference = False

        def simulate(self, initial, times):
            return np.zeros((len(initial), len(times), 1))

    assert D.simulated_ground_truth(Cheap(), np.zeros((2, 1)), np.arange(3.0), tmp_path).shape == (2, 3, 1)
    assert not list(tmp_path.iterdir())
