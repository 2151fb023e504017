"""A task of several seed groups (a population's batch) steps each group as its own task would."""

import pytest
import torch

import tasks


@pytest.mark.parametrize("name", ["cartpole", "hopper", "ant"])
def test_each_seed_group_steps_as_its_own_task(name):
    seeds, envs = [3, 5, 3], 4
    together = tasks.make(name, len(seeds) * envs, seed=seeds, episode_length=6)
    alone = [tasks.make(name, envs, seed=s, episode_length=6) for s in seeds]
    obs = together.reset()
    for g, task in enumerate(alone):
        assert torch.equal(obs[g * envs:(g + 1) * envs], task.reset())
    gen = torch.Generator().manual_seed(0)
    for _ in range(8):  # past the episode length: resets draw each group's own initial states
        action = torch.rand(len(seeds) * envs, together.num_act, generator=gen) * 2 - 1
        obs, reward, done, _ = together.step(action)
        for g, task in enumerate(alone):
            rows = slice(g * envs, (g + 1) * envs)
            o, r, d, _ = task.step(action[rows])
            assert torch.equal(obs[rows], o) and torch.equal(reward[rows], r) and torch.equal(done[rows], d)
    state = together.get_state()
    assert state["rng"].tolist() == [*seeds, alone[0].get_state()["rng"][1].item()]
    together.set_state(state)
    with pytest.raises(ValueError, match="rng"):
        together.set_state({**state, "rng": alone[0].get_state()["rng"]})
