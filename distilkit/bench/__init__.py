"""``distilkit bench``: one module per benchmark, each registering its cases in :mod:`distilkit.bench.base`;
:mod:`distilkit.bench.runner` runs them and prints the table. Importing the package registers every benchmark, in
the order ``distilkit bench`` runs them when given no name."""

from distilkit.bench import objectives, bev, sampler, complete, training, kitti, sparse, networks  # noqa: F401  (register)
from distilkit.bench import teacher_store  # noqa: F401  (register)
from distilkit.bench import step  # noqa: F401  (register; after networks: distilkit bench runs it last)
from distilkit.bench.base import BENCHES, Case
from distilkit.bench.runner import run_bench

__all__ = ["BENCHES", "Case", "run_bench"]
