"""CounterRNG's seed groups: each group of rows draws exactly what a generator of its own would draw."""

import pytest
import torch

from tasks.rng import CounterRNG


def test_each_seed_group_draws_what_its_own_generator_draws():
    seeds = [4, 9, 4, 123]
    rows = 8
    grouped = CounterRNG(len(seeds) * rows, 5, seed=seeds, device="cpu")
    alone = [CounterRNG(rows, 5, seed=s, device="cpu") for s in seeds]
    for _ in range(3):
        draw = grouped.uniform(torch.float64)
        for g, rng in enumerate(alone):
            assert torch.equal(draw[g * rows:(g + 1) * rows], rng.uniform(torch.float64))
    # equal seeds draw equal numbers, different seeds different ones
    assert torch.equal(draw[:rows], draw[2 * rows:3 * rows])
    assert not torch.equal(draw[:rows], draw[rows:2 * rows])


def test_one_seed_is_the_ungrouped_generator_and_its_state_has_two_entries():
    a = CounterRNG(16, 3, seed=77, device="cpu")
    b = CounterRNG(16, 3, seed=[77], device="cpu")
    assert torch.equal(a.uniform(), b.uniform())
    assert a.get_state().tolist() == [77, 1]


def test_grouped_state_round_trips_and_rejects_other_shapes():
    rng = CounterRNG(6, 2, seed=[1, 2, 3], device="cpu")
    rng.uniform()
    state = rng.get_state()
    assert state.tolist() == [1, 2, 3, 1]
    nxt = rng.uniform()
    rng.set_state(state)
    assert torch.equal(rng.uniform(), nxt)
    with pytest.raises(ValueError, match="expected"):
        rng.set_state(torch.tensor([1, 0]))


def test_rows_must_split_evenly_into_groups():
    with pytest.raises(ValueError, match="equal seed groups"):
        CounterRNG(7, 2, seed=[1, 2], device="cpu")
