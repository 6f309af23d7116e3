"""The guiding state: STree invariants, normalised pmfs, the vMF mixture's
sampler against its density (MPG Sec. 5.5, supplemental Sec. 3.3)."""

from __future__ import annotations

import numpy as np
import pytest

from mpg import _core

from stats_util import sphere_gof, uniform_u


def _samples(N, seed=0, clusters=6):
    """Sub-path samples with clustered endpoints and directions."""
    rng = np.random.default_rng(seed)
    cD = rng.uniform(-1, 1, size=(clusters, 3))
    cL = rng.uniform(-1, 1, size=(clusters, 3))
    k = rng.integers(0, clusters, N)
    xD = (cD[k] + rng.normal(scale=0.15, size=(N, 3))).clip(-1, 1).astype(np.float32)
    xL = (cL[k] + rng.normal(scale=0.15, size=(N, 3))).clip(-1, 1).astype(np.float32)
    mu = rng.normal(size=(clusters, 3))
    d = mu[k] + rng.normal(scale=0.2, size=(N, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = rng.integers(1, 4, N)
    tau = rng.integers(0, 1 << 3, N) & ((1 << n) - 1)
    w = rng.exponential(size=N).astype(np.float32)
    return xD, xL, d.astype(np.float32), n.astype(np.int32), tau.astype(np.uint16), w


def test_subpath_sample_is_40_bytes():
    assert _core.SUBPATH_SAMPLE_BYTES == 40


@pytest.mark.parametrize("eps", [0.0, 0.1, 0.3])
def test_stree_invariants(eps):
    N = 20000
    xD, xL, d, n, tau, w = _samples(N)
    g = _core.GuidingState()
    g.build(xD, xL, d, n, tau, w, [-1, -1, -1], [1, 1, 1], c=1.0, epsilon=eps, max_depth=36)
    assert g.num_leaves > 10
    total_unfiltered = 0
    copies = 0
    for i in range(g.num_leaves):
        leaf = g.leaf(i)
        lo, hi = np.array(leaf["lo"]), np.array(leaf["hi"])
        filt = leaf["filtered"]
        k = len(filt)
        # leaf sizes respect the threshold unless the depth cap stopped them
        assert k <= g.threshold or leaf["depth"] >= 36
        assert leaf["unfiltered"] == int((~filt).sum())
        total_unfiltered += leaf["unfiltered"]
        copies += int(filt.sum())
        q = np.array([g.normalise(a, b) for a, b in zip(leaf["xD"], leaf["xL"])]).reshape(-1, 6)
        if k:
            inside = np.all((q >= lo - 1e-6) & (q <= hi + 1e-6), axis=1)
            # every unfiltered sample lies in its own leaf ...
            assert inside[~filt].all()
            # ... and every filtered copy within 2 eps x the extent of its box
            dist = np.maximum(np.maximum(lo - q, 0), q - hi) / (hi - lo)
            assert (dist[filt] <= 2 * eps + 1e-5).all()
    # each sample is stored unfiltered exactly once; copies only with filtering
    assert total_unfiltered == N
    assert (copies > 0) == (eps > 0)
    assert g.samples_stored == N + copies
    # the query finds the leaf holding a sample
    for j in range(0, N, 997):
        leaf = g.leaf(g.leaf_of(xD[j].tolist(), xL[j].tolist()))
        assert np.any(np.all(np.isclose(leaf["xD"], xD[j]), axis=1) & ~leaf["filtered"])


def test_pmfs_are_normalised():
    xD, xL, d, n, tau, w = _samples(5000, seed=1)
    g = _core.GuidingState()
    g.build(xD, xL, d, n, tau, w, [-1, -1, -1], [1, 1, 1])
    checked = 0
    for i in range(g.num_leaves):
        if len(g.leaf(i)["filtered"]) == 0:
            continue  # an empty leaf (all samples fell on the other side) has no distribution
        checked += 1
        tot = sum(g.pmf_n(i, k) for k in range(1, 17))
        assert tot == pytest.approx(1.0, abs=1e-5)
        for k in range(1, 4):
            if g.pmf_n(i, k) > 0:
                st = sum(g.pmf_tau(i, k, t) for t in range(1 << k))
                assert st == pytest.approx(1.0, abs=1e-5)
    assert checked > 5


def test_vmf_mixture_sampler_matches_its_density():
    """Chi-square of a leaf's mixture sampler against its pdf (significance 1e-4)."""
    rng = np.random.default_rng(3)
    N = 60
    d = rng.normal(size=(N, 3)) + np.array([0, 0, 2.0])
    xD = np.zeros((N, 3), np.float32)
    xL = np.zeros((N, 3), np.float32)
    g = _core.GuidingState()
    g.build(xD, xL, d.astype(np.float32), np.full(N, 2, np.int32), np.zeros(N, np.uint16),
            rng.exponential(size=N).astype(np.float32), [-1, -1, -1], [1, 1, 1], c=100.0)
    assert g.num_leaves == 1
    M = 400000
    s = g.sample_dir(0, 2, 0, uniform_u(M, 3, 4))
    assert np.isfinite(s).all()
    p, msg, integral, _ = sphere_gof(s, lambda v: g.pdf_dir(0, 2, 0, v.astype(np.float32)), M)
    assert p > 1e-4, msg
    assert integral == pytest.approx(1.0, abs=2e-3)
