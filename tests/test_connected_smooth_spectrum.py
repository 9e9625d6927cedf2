"""The smooth lower bound of lambda2 (controllers/connectivity/smooth_spectrum.py):
its defining equation, bounds, gradient against finite differences of eigvalsh,
and independence of the eigenvector basis on a degenerate spectrum."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from connected_helpers import preset_params
from controllers.connectivity.graph import link_weights, weighted_laplacian
from controllers.connectivity.smooth_spectrum import smooth_lambda2, smooth_lambda2_gradient
from sim.geometry import Boxes

spectra = st.lists(st.floats(1e-4, 5.0), min_size=1, max_size=34).map(lambda v: np.sort(np.array([0.0, *v])))


@settings(max_examples=300, deadline=None)
@given(values=spectra, kappa=st.floats(0.005, 1.0))
def test_solves_its_equation_and_stays_between_its_bounds(values, kappa):
    s, slope = smooth_lambda2(values, kappa)
    rest, lowest = values[1:], values[1]
    tau = kappa * s
    assert s == pytest.approx(lowest - tau * math.log(np.exp(-(rest - lowest) / tau).sum()), rel=1e-9, abs=1e-15)
    assert lowest / (1 + kappa * math.log(len(rest))) - 1e-12 <= s <= lowest + 1e-12
    assert np.all(slope >= 0) and slope.sum() <= 1 + 1e-9
    # Degree-one homogeneous: sum_k lambda_k ds/dlambda_k = s.
    assert float(slope @ rest) == pytest.approx(s, rel=1e-9)


def test_kappa_zero_is_lambda2():
    values = np.array([0.0, 0.3, 0.31, 2.0])
    s, slope = smooth_lambda2(values, 0.0)
    assert s == 0.3 and slope.tolist() == [1.0, 0.0, 0.0]


def _team(rng):
    base = np.array([[0, 0, 1], [1.2, 0.3, 1], [2.3, 0.2, 1.1], [1.0, 1.4, 1.0], [2.2, 1.5, 0.9], [3.3, 0.8, 1.0]])
    return base + rng.normal(0, 0.05, base.shape)


@pytest.mark.parametrize("kappa", [0.0, 0.05, 0.3])
def test_gradient_matches_finite_differences_of_eigvalsh(kappa):
    params = preset_params("office")
    boxes = Boxes.axis_aligned([[2.5, 3.0, 1.0]], [[0.3, 0.3, 2.0]])
    q = _team(np.random.default_rng(3))

    def value(points):
        return smooth_lambda2(np.linalg.eigvalsh(weighted_laplacian(link_weights(points, boxes, params).weights)),
                              kappa)[0]

    links = link_weights(q, boxes, params)
    eigenvalues, eigenvectors = np.linalg.eigh(weighted_laplacian(links.weights))
    s, gradient = smooth_lambda2_gradient(links, eigenvalues, eigenvectors, kappa)
    assert s == pytest.approx(value(q))
    step = 1e-6
    numeric = np.zeros_like(q)
    for i in range(len(q)):
        for d in range(3):
            e = np.zeros_like(q)
            e[i, d] = step
            numeric[i, d] = (value(q + e) - value(q - e)) / (2 * step)
    np.testing.assert_allclose(gradient, numeric, atol=1e-6 * np.abs(numeric).max())


def test_gradient_does_not_depend_on_the_basis_of_a_degenerate_eigenspace():
    # A symmetric star: the centre's two leaf pairs give lambda2 = lambda3 exactly.
    params = preset_params("office")
    q = np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [-2.0, 0.0, 1.0], [0.0, 2.0, 1.0], [0.0, -2.0, 1.0]])
    links = link_weights(q, None, params)
    values, vectors = np.linalg.eigh(weighted_laplacian(links.weights))
    assert values[2] - values[1] < 1e-12
    rotation = np.eye(len(q))
    angle = 0.7
    rotation[1:3, 1:3] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    _, first = smooth_lambda2_gradient(links, values, vectors, 0.05)
    _, second = smooth_lambda2_gradient(links, values, vectors @ rotation, 0.05)
    np.testing.assert_allclose(first, second, atol=1e-12)
