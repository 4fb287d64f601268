"""The laws' tail probabilities and quantiles against their closed forms where one exists:
χ²(2) is the exponential law of mean 2, Student's t(1) the Cauchy law, and F(2, d) has
P(X > x) = (1 + 2x/d)^(−d/2)."""

import numpy as np

from jaxtable._distributions import chi2_ppf, chi2_sf, f_sf, t_ppf, t_sf

X = np.array([0.0, 1e-3, 0.4, 1.0, 2.5, 7.0, 30.0])
Q = np.array([1e-6, 0.025, 0.3, 0.5, 0.9, 0.975, 1 - 1e-9])


def test_chi2_of_two_degrees_is_the_exponential_law():
    np.testing.assert_allclose(chi2_sf(X, 2), np.exp(-X / 2), rtol=1e-14)
    np.testing.assert_allclose(chi2_ppf(Q, 2), -2 * np.log1p(-Q), rtol=1e-12)
    np.testing.assert_allclose(chi2_sf(chi2_ppf(Q, 7.5), 7.5), 1 - Q, rtol=1e-9)


def test_student_t_of_one_degree_is_the_cauchy_law():
    x = np.concatenate([-X, X])
    np.testing.assert_allclose(t_sf(x, 1), 0.5 - np.arctan(x) / np.pi, rtol=1e-13)
    q = Q[:-1]  # (1 − 1e-9 is stored to ~1e-7 of 1e-9, the quantile to no better)
    np.testing.assert_allclose(t_ppf(q, 1), np.tan(np.pi * (q - 0.5)), rtol=1e-9, atol=1e-15)


def test_f_with_two_numerator_degrees_has_its_power_law_tail():
    for d in (1.0, 5.0, 40.0):
        np.testing.assert_allclose(f_sf(X, 2, d), (1 + 2 * X / d) ** (-d / 2), rtol=1e-13)


def test_below_the_support_the_tail_holds_everything():
    assert chi2_sf(-0.3, 4) == 1.0 and f_sf(-2.0, 3, 10) == 1.0
