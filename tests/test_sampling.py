"""GlobalBatchSampler: the same global batches for any number of ranks, per epoch, after a restart."""
import pytest
import torch
from torch.utils.data import DataLoader

from lnf.training.sampling import GlobalBatchSampler


def _batches(n, batch_size, world_size, epoch, drop_last=True, shuffle=True):
    """Global batches as sets: the union over ranks of each rank's DataLoader batch at each step."""
    per_rank = []
    for rank in range(world_size):
        sampler = GlobalBatchSampler(n, batch_size, shuffle=shuffle, seed=3, drop_last=drop_last, rank=rank,
                                     world_size=world_size)
        sampler.set_epoch(epoch)
        loader = DataLoader(torch.arange(n), batch_size=sampler.per_rank_batch_size, sampler=sampler)
        per_rank.append([b.tolist() for b in loader])
        assert len(sampler) == sum(len(b) for b in per_rank[-1])
    steps = {len(b) for b in per_rank}
    assert len(steps) == 1, "every rank must take the same number of steps"
    return [sorted(sum((per_rank[r][s] for r in range(world_size)), [])) for s in range(steps.pop())]


@pytest.mark.parametrize("world_size", [2, 4])
def test_ranks_share_the_single_process_batches(world_size):
    for epoch in (0, 1):
        assert _batches(50, 8, world_size, epoch) == _batches(50, 8, 1, epoch)
    assert _batches(50, 8, 1, 0) != _batches(50, 8, 1, 1), "a new order every epoch"


def test_order_depends_only_on_seed_and_epoch():
    a, b = GlobalBatchSampler(20, 4, seed=5), GlobalBatchSampler(20, 4, seed=5)
    list(a)  # iterating does not advance anything: a restarted run sees the same epoch order
    a.set_epoch(7), b.set_epoch(7)
    assert list(a) == list(b)
    assert sorted(a) == list(range(20))


def test_last_batch_and_no_shuffle():
    assert len(_batches(10, 4, 1, 0, drop_last=True)) == 2
    batches = _batches(10, 4, 2, 0, drop_last=False, shuffle=False)
    assert batches == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9]]
    # a last batch smaller than the number of ranks would leave one rank without a step: dropped
    assert _batches(9, 4, 2, 0, drop_last=False, shuffle=False)[-1] == [4, 5, 6, 7]


def test_bad_settings_are_clear_errors():
    with pytest.raises(ValueError, match="multiple of the number of processes 2"):
        GlobalBatchSampler(10, 5, world_size=2)
    with pytest.raises(ValueError, match="rank"):
        GlobalBatchSampler(10, 4, rank=2, world_size=2)
    with pytest.raises(ValueError, match="cannot be shared"):
        GlobalBatchSampler(1, 2, world_size=2)
