"""The ring buffer of transitions: once full, each add overwrites the oldest rows, and a checkpoint restores it."""
import torch

from drop_engine.replay_buffer import ReplayBuffer


def _rows(first: int, n: int) -> dict[str, torch.Tensor]:
    """Transitions numbered first..first+n-1, every field carrying its row's number."""
    ids = torch.arange(first, first + n, dtype=torch.float32)
    obs = ids[:, None].repeat(1, 2)
    return {"obs": obs, "act": -ids[:, None], "rew": ids, "next_obs": obs + 0.5, "done": ids % 2}


def _held(buffer: ReplayBuffer) -> list[int]:
    """The row numbers in each slot, checked to agree across the fields."""
    obs, act, rew, next_obs, done = buffer.take(torch.arange(buffer.size))
    assert torch.equal(obs[:, 0], rew) and torch.equal(obs[:, 1], rew) and torch.equal(act[:, 0], -rew)
    assert torch.equal(next_obs, obs + 0.5) and torch.equal(done, rew % 2)
    return rew.int().tolist()


def test_adds_wrap_around_and_overwrite_the_oldest_rows():
    buffer = ReplayBuffer(5, obs_dim=2, act_dim=1)
    buffer.add(**_rows(0, 3))
    assert (len(buffer), buffer.ptr, _held(buffer)) == (3, 3, [0, 1, 2])
    buffer.add(**_rows(3, 4))  # rows 3 and 4 fill the ring, 5 and 6 overwrite 0 and 1
    assert (len(buffer), buffer.ptr, _held(buffer)) == (5, 2, [5, 6, 2, 3, 4])
    buffer.add(**_rows(7, 3))
    assert (len(buffer), buffer.ptr, _held(buffer)) == (5, 0, [5, 6, 7, 8, 9])


def test_an_add_larger_than_the_ring_keeps_the_newest_rows():
    buffer = ReplayBuffer(4, obs_dim=2, act_dim=1)
    buffer.add(**_rows(0, 1))
    buffer.add(**_rows(1, 6))  # only rows 3..6 fit; they are written from the pointer on
    assert (len(buffer), buffer.ptr, _held(buffer)) == (4, 1, [6, 3, 4, 5])


def test_samples_come_from_filled_slots_only():
    buffer = ReplayBuffer(100, obs_dim=2, act_dim=1)
    buffer.add(**_rows(10, 3))
    torch.manual_seed(0)
    assert set(buffer.sample(1000)[2].int().tolist()) == {10, 11, 12}


def test_a_wrapped_buffer_resumes_from_its_state():
    buffer = ReplayBuffer(5, obs_dim=2, act_dim=1)
    buffer.add(**_rows(0, 3))
    buffer.add(**_rows(3, 4))
    restored = ReplayBuffer(5, obs_dim=2, act_dim=1)
    restored.load_state_dict(buffer.state_dict())
    restored.add(**_rows(7, 1))  # overwrites the oldest row, 2, as the original would
    buffer.add(**_rows(7, 1))
    assert _held(restored) == _held(buffer) == [5, 6, 7, 3, 4]
