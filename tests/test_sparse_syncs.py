"""Host syncs on the sparse path (``tests/host_syncs.py`` counts them: CUDA's sync debug mode on a GPU, the ops that
would sync on the CPU): a neighbour map costs a few whatever its kernel (the offsets are looked up together, not one
by one), and a convolution on a built map — forward and backward — none on the torch path."""

from __future__ import annotations

import torch

from distilkit.sparse import SparseConv3d, SparseConvTensor, SubMConv3d
from distilkit.sparse.rulebook import sort_keys, strided, submanifold
from host_syncs import host_syncs


def scene(device: torch.device, n: int = 2000, size: int = 24) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    c = torch.unique(torch.randint(0, size, (n, 3), generator=g), dim=0)
    b = torch.randint(0, 2, (len(c), 1), generator=g)
    return torch.cat([b, c], 1).int().to(device)


def test_a_map_costs_a_few_host_syncs_whatever_its_kernel(device) -> None:
    idx = scene(device)
    shape = (24, 24, 24)
    keys = sort_keys(idx, shape)
    for kernel in ((3, 3, 3), (5, 5, 5)):
        with host_syncs(device) as syncs:
            book = submanifold(idx, shape, kernel, (1, 1, 1), keys)
        assert book.pairs > 0 and len(syncs) <= 2, syncs  # the found pairs' positions, the counts (was ~3 per offset)
        with host_syncs(device) as syncs:
            book = strided(idx, shape, kernel, (2, 2, 2), (1, 1, 1), (1, 1, 1))
        assert book.pairs > 0 and len(syncs) <= 3, syncs  # + unique's size


def test_a_convolution_on_a_built_map_syncs_with_the_host_not_once(device) -> None:
    """Forward and backward of a submanifold and a strided layer whose maps exist, on the torch path, with PyTorch's
    deterministic algorithms on (CUDA's deterministic index_add_ would sort and read the index's range)."""
    torch.manual_seed(0)
    idx = scene(device)
    layers = [SubMConv3d(4, 8, 3, indice_key="a").to(device), SparseConv3d(8, 4, 3, stride=2, padding=1).to(device)]
    feats = torch.randn(len(idx), 4, device=device, requires_grad=True)
    x = SparseConvTensor(feats, idx, (24, 24, 24), 2)
    books = [layers[0].rulebook(x)]
    was = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        from distilkit.sparse import backend

        with backend.using("torch"):
            y = layers[0]._run(x, books[0], len(idx))
            book = strided(idx, (24, 24, 24), (3, 3, 3), (2, 2, 2), (1, 1, 1), (1, 1, 1))
            rows = book.out_indices.shape[0]
            with host_syncs(device) as syncs:
                z = layers[1]._run(x.derived(y), book, rows)
                y2 = layers[0]._run(x, books[0], len(idx))
                loss = z.square().sum() + y2.square().sum()
                loss.backward()
    finally:
        torch.use_deterministic_algorithms(was[0], warn_only=was[1])
    assert feats.grad is not None and bool(feats.grad.abs().sum() > 0)
    assert syncs == [], syncs
