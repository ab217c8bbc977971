"""The batched-ensemble helpers must not change what the networks compute, only how much of it runs."""
import torch

from drop_engine.config import DynamicsConfig
from drop_engine.dynamics import GaussianEnsemble
from drop_engine.nn import RowsByMember, in_row_chunks


def _model() -> GaussianEnsemble:
    torch.manual_seed(0)
    return GaussianEnsemble(4, 2, DynamicsConfig(members=5, elites=3, hidden=32, layers=2))


def test_rows_by_member_matches_running_every_member():
    model = _model()
    obs, act = torch.randn(1000, 4), torch.randn(1000, 2)
    member = torch.randint(0, 3, (1000,))
    with torch.no_grad():
        full_mean, full_logvar = model(obs, act, model.elites)
        groups = RowsByMember(member, 3)
        mean, logvar = model(groups.gather(obs), groups.gather(act), model.elites)
    rows = torch.arange(1000)
    assert groups.index.shape[0] == 3 and groups.index.shape[1] == int(torch.bincount(member).max())
    torch.testing.assert_close(groups.scatter(mean), full_mean[member, rows], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(groups.scatter(logvar), full_logvar[member, rows], rtol=1e-5, atol=1e-5)


def test_rows_by_member_with_an_empty_member():
    member = torch.tensor([0, 0, 2, 0, 2])
    groups = RowsByMember(member, 3)
    values = torch.arange(5.0) * 10
    per_member = groups.gather(values) + torch.tensor([[0.0], [100.0], [200.0]])
    assert groups.scatter(per_member).tolist() == [0.0, 10.0, 220.0, 30.0, 240.0]


def test_in_row_chunks_equals_one_call():
    model = _model()
    obs, act = torch.randn(1300, 4), torch.randn(1300, 2)
    with torch.no_grad():
        whole = model(obs, act)
        chunked = in_row_chunks(model, obs, act, out_dim=1, rows=256)
        per_member = in_row_chunks(lambda o, a: model(o, a), obs.expand(5, -1, -1), act.expand(5, -1, -1),
                                   in_dim=1, out_dim=1, rows=500)
    for got in (chunked, per_member):
        assert got[0].shape == (5, 1300, 5)
        torch.testing.assert_close(got[0], whole[0], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(got[1], whole[1], rtol=1e-5, atol=1e-5)
