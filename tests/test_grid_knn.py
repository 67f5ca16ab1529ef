"""``distilkit.geometry.knn.grid_knn``, JS3C-Net's exact k nearest supports on the points' device: against a naive
int64 brute force (the full distance matrix, sorted by distance then index) on clouds full of ties, against SciPy's
k-d tree where nothing ties, its one host sync, and the JS3C-Net paper network unchanged by it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor

from distilkit.geometry.knn import grid_knn
from host_syncs import host_syncs

SMALL_BLOCKS = {"query_block": 3, "support_block": 2, "group": 1, "max_bytes": 1}  # padding, chunks, a long loop


def _naive(query: Tensor, support: Tensor, k: int) -> np.ndarray:
    """The full (Q, S) int64 squared distances, each row lexsorted by (distance, index), the first min(k, S)."""
    q, s = query.cpu().numpy().astype(np.int64), support.cpu().numpy().astype(np.int64)
    d2 = ((q[:, None, :] - s[None, :, :]) ** 2).sum(-1)
    index = np.broadcast_to(np.arange(len(s)), d2.shape)
    return np.lexsort((index, d2), axis=1)[:, :min(k, len(s))].reshape(len(q), min(k, len(s)))


def _grid_knn_scipy(query: Tensor, support: Tensor, k: int) -> Tensor:
    """The previous implementation of ``distilkit_adapters.js3cnet.paper.grid_knn`` (a SciPy k-d tree on the host),
    kept as the reference the network is compared with."""
    from scipy.spatial import cKDTree

    k = min(k, len(support))
    if len(query) == 0 or k == 0:
        return torch.zeros((len(query), k), dtype=torch.long, device=query.device)
    q, s = query.cpu().numpy(), support.cpu().numpy()
    extra = min(k + 8, len(s))
    _, cand = cKDTree(s.astype(np.float64)).query(q.astype(np.float64), extra)
    cand = cand.reshape(len(q), extra)
    d2 = ((s[cand] - q[:, None]) ** 2).sum(-1)
    order = np.lexsort((cand, d2), axis=1)  # by distance, then index
    cand, d2 = np.take_along_axis(cand, order, 1), np.take_along_axis(d2, order, 1)
    open_tie = (d2[:, k - 1] == d2[:, -1]) & (extra < len(s))
    for i in np.nonzero(open_tie)[0]:  # the tie group may hold supports the tree did not return
        full = ((s - q[i]) ** 2).sum(-1)
        cand[i, :k] = np.lexsort((np.arange(len(s)), full))[:k]
    return torch.from_numpy(np.ascontiguousarray(cand[:, :k])).to(query.device)


def test_it_matches_a_naive_brute_force_on_clouds_full_of_ties_and_duplicates(device) -> None:
    g = torch.Generator().manual_seed(0)
    for trial in range(16):
        half = (1, 2, 4, 40)[trial % 4]  # coordinates in [-half, half]: many equidistant supports
        n_q, n_s = int(torch.randint(1, 200, (1,), generator=g)), int(torch.randint(1, 200, (1,), generator=g))
        query = torch.randint(-half, half + 1, (n_q, 3), generator=g)
        support = torch.randint(-half, half + 1, (n_s, 3), generator=g)
        support = torch.cat([support, support[torch.randint(0, n_s, (n_s // 3,), generator=g)]])  # duplicates
        for k in (1, 8, 3 * len(support) // 4, len(support) + 5):
            want = _naive(query, support, k)
            for blocks in ({}, SMALL_BLOCKS):
                got = grid_knn(query.to(device), support.to(device), k, **blocks)
                assert got.device.type == device.type and got.dtype == torch.long
                assert np.array_equal(got.cpu().numpy(), want), (trial, k, blocks)


def test_it_takes_every_support_when_k_is_larger_and_empty_sets_give_empty_rows(device) -> None:
    g = torch.Generator().manual_seed(1)
    query, support = torch.randint(0, 9, (30, 3), generator=g).to(device), torch.randint(0, 9, (5, 3), generator=g)
    got = grid_knn(query, support.to(device), 8)
    assert got.shape == (30, 5) and np.array_equal(got.cpu().numpy(), _naive(query, support, 8))
    assert torch.equal(grid_knn(query, support[:1].to(device), 8).cpu(), torch.zeros(30, 1, dtype=torch.long))
    for q, s, k, shape in ((query[:0], support, 8, (0, 5)), (query, support[:0], 8, (30, 0)),
                           (query, support, 0, (30, 0)), (query[:0], support[:0], 3, (0, 0))):
        out = grid_knn(q, s.to(device), k)
        assert out.shape == shape and out.dtype == torch.long and out.device.type == device.type


def test_it_matches_scipys_kd_tree_where_nothing_ties() -> None:
    from scipy.spatial import cKDTree

    g = torch.Generator().manual_seed(2)
    query = torch.randint(-30000, 30000, (1500, 3), generator=g)
    support = torch.randint(-30000, 30000, (1000, 3), generator=g)
    k = 8
    d2 = ((query[:, None].double() - support[None].double()) ** 2).sum(-1)
    nearest = torch.sort(d2, 1).values[:, :k + 1]
    distinct = (nearest[:, 1:] > nearest[:, :-1]).all(1)  # the k + 1 nearest at k + 1 distances
    assert distinct.float().mean() > 0.99
    _, want = cKDTree(support.numpy().astype(np.float64)).query(query.numpy().astype(np.float64), k)
    got = grid_knn(query, support, k)
    assert np.array_equal(got[distinct].numpy(), want[distinct.numpy()])


def test_it_refuses_floats_and_coordinates_too_wide_for_exact_keys() -> None:
    with pytest.raises(TypeError, match="integer coordinates"):
        grid_knn(torch.zeros(3, 3), torch.zeros(4, 3), 2)
    with pytest.raises(ValueError, match=r"\(Q, 3\) and \(S, 3\)"):
        grid_knn(torch.zeros(3, 2, dtype=torch.long), torch.zeros(4, 2, dtype=torch.long), 2)
    wide = torch.tensor([[0, 0, 0], [1 << 30, 0, 0]])
    with pytest.raises(ValueError, match="exceed float64's exact integers"):
        grid_knn(wide, wide, 1)


def test_the_search_syncs_with_the_host_once(device) -> None:
    """One sync (the number of candidate support blocks of each query block, which sizes the loop), however many
    query blocks, candidates, steps and chunks: here a hundred or more of each."""
    g = torch.Generator().manual_seed(3)
    query = torch.randint(0, 64, (2000, 3), generator=g).to(device)
    support = torch.randint(0, 64, (1000, 3), generator=g).to(device)
    with host_syncs(device) as syncs:
        got = grid_knn(query, support, 8, query_block=8, support_block=4, group=2, max_bytes=1 << 17)
    assert len(syncs) == 1, syncs
    rows = torch.randperm(2000, generator=g)[:200]
    assert np.array_equal(got[rows.to(device)].cpu().numpy(), _naive(query[rows.to(device)], support, 8))


def test_the_js3cnet_paper_network_is_bit_identical_with_the_previous_search(monkeypatch) -> None:
    """The paper network's forward (every output) and gradients with ``grid_knn`` as it is and as it was
    (``_grid_knn_scipy``), on a batch of two tiny scans; its searches run the candidate loop (252 and 233 supports:
    16 blocks, 4 seeded)."""
    import distilkit_adapters.js3cnet.paper as paper
    from test_js3cnet_paper import batch, js3c

    sample, calls = batch(), []

    def run(search):  # (outputs, gradients) of one training step
        def recorded(query: Tensor, support: Tensor, k: int) -> Tensor:
            calls.append(len(support))
            return search(query, support, k)

        monkeypatch.setattr(paper, "grid_knn", recorded)
        model = js3c().train()
        out = model(sample)
        (out["logits"].sum() + out["point_logits"].sum() + out["completion"].feats.sum()).backward()
        tensors = {n: getattr(v, "feats", v) for n, v in out.items() if isinstance(getattr(v, "feats", v), Tensor)}
        return tensors, {n: p.grad for n, p in model.named_parameters()}

    was, was_grads = run(_grid_knn_scipy)
    now, now_grads = run(paper.exact_grid_knn)
    assert calls[:2] == calls[2:] and min(calls) > 4 * 16
    assert was.keys() == now.keys() and was_grads.keys() == now_grads.keys()
    for name in was:
        assert torch.equal(was[name], now[name]), name
    for name in was_grads:
        assert (was_grads[name] is None) == (now_grads[name] is None), name
        assert was_grads[name] is None or torch.equal(was_grads[name], now_grads[name]), name
