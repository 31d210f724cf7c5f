"""The sample table: N points in the unit cube of the varied keys, drawn by scipy.stats.qmc
from a recorded seed, mapped to values by each key's inverse CDF (distributions.py).

    lhs       Latin hypercube: each key's range cut in N equally likely strata, each stratum
              hit exactly once (any N)
    sobol     scrambled Sobol points (N a power of 2 keeps their balance)
    saltelli  Saltelli's scheme for first-order and total Sobol indices: two independent
              Sobol blocks A and B (N rows each) and, per key i, A with column i taken from B
              (AB_i): N (d + 2) runs; statistics.py estimates the indices from the blocks

The same seed, method, N and distributions give the same table, bit for bit: a study is
repeated by its study.json.
"""
import numpy as np
from scipy.stats import qmc

from .distributions import UsageError

METHODS = ("lhs", "sobol", "saltelli")


class Design:
    """rows: [(block, index in block, u vector)], values: per row, the value of each key."""

    def __init__(self, dists, rows):
        self.dists = dists
        self.rows = rows
        cols = [d.ppf(np.array([r[2][j] for r in rows])) for j, d in enumerate(dists)]
        self.values = [[cols[j][i] for j in range(len(dists))] for i in range(len(rows))]

    def __len__(self):
        return len(self.rows)


def _unit_points(method, d, n, seed):
    if method == "lhs":
        return qmc.LatinHypercube(d=d, seed=seed).random(n)
    if method == "sobol":
        return qmc.Sobol(d=d, scramble=True, seed=seed).random(n)
    raise ValueError(method)


def make_design(dists, n, method, seed):
    if method not in METHODS:
        raise UsageError(f"--sampling '{method}': one of {', '.join(METHODS)}")
    if n < 1:
        raise UsageError(f"--samples {n}: must be at least 1")
    d = len(dists)
    if d == 0:
        # Nothing varied (a trajectory sweep alone): one sample, the scene's values.
        if n != 1:
            raise UsageError(f"--samples {n}: nothing is varied (no --vary), so there is one sample per trajectory")
        return Design(dists, [("design", 0, np.zeros(0))])
    if method in ("sobol", "saltelli") and n & (n - 1):
        raise UsageError(f"--samples {n}: Sobol points need a power of 2 (e.g. {1 << (n - 1).bit_length()})")
    if method != "saltelli":
        u = _unit_points(method, d, n, seed)
        return Design(dists, [("design", i, u[i]) for i in range(n)])
    ab = qmc.Sobol(d=2 * d, scramble=True, seed=seed).random(n)
    a, b = ab[:, :d], ab[:, d:]
    rows = [("A", i, a[i]) for i in range(n)] + [("B", i, b[i]) for i in range(n)]
    for j, dist in enumerate(dists):
        abj = a.copy()
        abj[:, j] = b[:, j]
        rows += [(f"AB:{dist.key}", i, abj[i]) for i in range(n)]
    return Design(dists, rows)
