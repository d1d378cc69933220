"""synth.fastrand: the compiled ziggurat draws N(0, 1) exactly in distribution, reproducibly."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from synth.fastrand import _F, _K, _W, _ziggurat, standard_normal


@pytest.fixture(scope="module")
def sample():
    return standard_normal(np.random.default_rng(5), 2_000_000, np.float64)


def test_moments_and_goodness_of_fit(sample):
    n = sample.size
    assert abs(sample.mean()) < 4 / np.sqrt(n)                      # 4 standard errors
    assert abs(sample.std() - 1) < 4 * np.sqrt(0.5 / n)
    assert abs(stats.skew(sample)) < 4 * np.sqrt(6 / n)
    assert abs(stats.kurtosis(sample)) < 4 * np.sqrt(24 / n)
    assert stats.kstest(sample, "norm").pvalue > 1e-3
    # 50 equal-probability bins: chi-square with 49 degrees of freedom
    edges = stats.norm.ppf(np.linspace(0, 1, 51))
    counts = np.histogram(sample, edges)[0]
    assert stats.chisquare(counts).pvalue > 1e-3


@pytest.mark.parametrize("t", [1.0, 2.0, 3.0, 3.442619855899, 4.0])
def test_tails_match_the_normal(sample, t):
    """The layers, the wedges and the tail beyond R = 3.4426 (its own sampler) all have the
    normal's mass: P(|x| > t) within 5 binomial standard errors."""
    p = 2 * stats.norm.sf(t)
    got = np.mean(np.abs(sample) > t)
    assert abs(got - p) < 5 * np.sqrt(p * (1 - p) / sample.size) + 1e-7, (got, p)


def test_reproducible_and_shaped():
    a = standard_normal(np.random.default_rng(3), (48, 64))
    b = standard_normal(np.random.default_rng(3), (48, 64))
    assert a.shape == (48, 64) and a.dtype == np.float32 and np.array_equal(a, b)
    rng = np.random.default_rng(3)
    c = standard_normal(rng, (48, 64))
    d = standard_normal(rng, (48, 64))            # the generator advances
    assert np.array_equal(a, c) and not np.array_equal(c, d)


def test_a_sample_never_straddles_two_word_buffers():
    """Words running out mid-sample (a wedge or tail rejection at the end of the buffer) stop the
    fill; the caller's next buffer starts the sample again, so filling in pieces is exact."""
    words = np.random.default_rng(9).bit_generator.random_raw(5000)
    out = np.empty(4000)
    n = _ziggurat(words, out, 0, _K, _W, _F)
    assert 4000 * 0.97 < n <= 4000
    part = np.empty(4000)
    k = _ziggurat(words[:100], part, 0, _K, _W, _F)
    assert k <= 100 and np.array_equal(part[:k], out[:k])
