"""Probability that a match (or a hypothetical new match in a gap) is correct, from its inversions
(Talker §5, Eq. 12; Teng & Dong Eq. 6-9). See the package docstring for the model.

``P(H | G)`` has two implementations: ``"gaussian"`` (Talker's fast version, moments of k beta nodes, O(1) per
entry, the only one the search-range table uses) and ``"exact"`` (hypergeometric sums, Numba kernel
``_exact_lik_good`` in :mod:`._kernels`, O(|S_beta| H) per entry). ``P(H | B)`` is uniform on
:func:`bad_inversion_range`.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from ._kernels import _exact_lik_good
from .ranks import inversions_per_match

__all__ = [
    "PROBABILITY_METHODS",
    "OrderNoise",
    "order_noise",
    "bad_inversion_range",
    "good_inversion_moments",
    "probability_correct",
]

PROBABILITY_METHODS = ("gaussian", "exact")  # models of P(H | G), see probability_correct
_P_G_CLIP = (0.01, 0.99)  # prior P_G clipped away from 0/1 so neither hypothesis is ruled out a priori
_OUT_OF_RANGE = 1e-3  # P(H|B) outside [H_lo, H_hi], relative to the in-range value
_EXACT_NSD = 8.0  # "exact": beta summed over mean +- 8 sd (hypergeometric), intersected with the support


def bad_inversion_range(left1, n_others, n_good_others):
    """Bounds ``[H_lo, H_hi]`` of the uniform model of ``P(H | B)`` (Talker §5; bounds derived here).

    Derivation. Normalize ranks: ``x = l1 / n_o`` (image 1), ``y`` (image 2). Under A1-A3 the ``G = n_good_others``
    correct matches lie on the monotone diagonal and the ``B = n_o - G`` incorrect ones are independent and uniform.
    A match at ``(x, y)`` then has on average

        ``H(y) = G |x - y| + B (x (1 - y) + (1 - x) y)``

    inversions (correct matches between x and y in rank, plus incorrect ones in the two off quadrants). An incorrect
    match has ``y ~ U[0, 1]`` independent of ``x``, so ``H`` sweeps the convex piecewise-linear ``H(y)``; the density is
    piecewise constant (1/|dH/dy| per branch), which Talker approximates as uniform between its extremes:
    ``H_hi = max(H(0), H(1)) = n_o max(x, 1 - x)`` (exact: at ``y = 0`` every left match is an inversion) and
    ``H_lo = min(H(x), H(0), H(1))`` with ``H(x) = 2 B x (1 - x)``, lowered by two standard deviations of the
    fluctuation at ``y = x`` (``H^l, H^r`` ~ Binomial(B, x(1-x)) each, Var ~ 2 B x (1 - x)) and by 1 (discreteness).
    ``H(x)`` is Talker's E[H | i in G]: a wrong match at the consistent place cannot be told apart by order.

    Args:
        left1: matches left of the match/gap in image 1 (scalar or array). n_others: other matches.
        n_good_others: correct ones among them (float).

    Returns:
        ``(H_lo, H_hi)`` float arrays (broadcast of ``left1``).
    """
    l1 = np.asarray(left1, dtype=np.float64)
    no = max(float(n_others), 1.0)
    g = min(max(float(n_good_others), 0.0), no)
    b = no - g
    x = np.clip(l1 / no, 0.0, 1.0)
    hx = 2.0 * b * x * (1.0 - x)
    h0 = no * x
    h1 = no * (1.0 - x)
    lo = np.minimum(np.minimum(hx, h0), h1) - 2.0 * np.sqrt(2.0 * b * x * (1.0 - x)) - 1.0
    return np.maximum(lo, 0.0), np.maximum(h0, h1)


@functools.lru_cache(maxsize=16)
def _hermite_nodes(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Hermite (probabilists') nodes and normalized weights for k points (cached; read-only arrays)."""
    nodes, weights = np.polynomial.hermite_e.hermegauss(k)
    weights = weights / weights.sum()
    nodes.flags.writeable = False
    weights.flags.writeable = False
    return nodes, weights


def _beta_moments(left, n_others, n_bad, num_beta):
    """Mean and second moment of Talker's k node values of beta ~ Hyp(left draws; n_others, n_bad)."""
    left = np.asarray(left, dtype=np.float64)
    no = max(float(n_others), 1.0)
    nb = min(max(float(n_bad), 0.0), no)
    p = nb / no
    mean = left * p
    var = left * p * (1.0 - p) * (no - left) / max(no - 1.0, 1.0)
    sd = np.sqrt(np.maximum(var, 0.0))
    nodes, weights = _hermite_nodes(max(int(num_beta), 1))
    lo_s = np.maximum(0.0, left - (no - nb))[..., None]
    hi_s = np.minimum(left, nb)[..., None]
    b = np.clip(mean[..., None] + sd[..., None] * nodes, lo_s, np.maximum(hi_s, lo_s))
    return (b * weights).sum(-1), (b * b * weights).sum(-1)


def _cell_moments(m1, s1, m2, s2, nb, var_floor):
    """Mean and variance of H | G from the beta moments (broadcasting); see module docstring."""
    if nb < 1e-9:
        mu = np.zeros(np.broadcast(m1, m2).shape)
        return mu, mu + var_floor
    mu = m1 + m2 - 2.0 * m1 * m2 / nb
    e2 = s1 + s2 + 2.0 * m1 * m2 - 4.0 * (s1 * m2 + m1 * s2) / nb + 4.0 * s1 * s2 / (nb * nb)
    var_mu = np.maximum(e2 - mu * mu, 0.0)
    vh = 2.0 * (nb * m1 - s1) * (nb * m2 - s2) / (nb * nb * (nb - 1.0)) if nb > 1.0 else 0.0 * mu
    return mu, np.maximum(vh, 0.0) + var_mu + var_floor


def good_inversion_moments(left1, left2, n_others, n_good_others, num_beta=5, var_floor=1.0):
    """Mean and variance of ``H | G`` (Talker Eq. 7 averaged over his k beta values; "gaussian" model).

    Args:
        left1, left2: matches left of the match/gap in image 1 / image 2 (broadcastable arrays).
        n_others: number of other matches; n_good_others: correct ones among them (float).
    """
    nb = max(float(n_others) - float(n_good_others), 0.0)
    m1, s1 = _beta_moments(left1, n_others, nb, num_beta)
    m2, s2 = _beta_moments(left2, n_others, nb, num_beta)
    return _cell_moments(m1, s1, m2, s2, nb, var_floor)


def _posterior(log_pg_lik, h, left1, n_others, n_good_others, p_good):
    lo, hi = bad_inversion_range(left1, n_others, n_good_others)
    width = hi - lo + 1.0
    inside = (h >= lo) & (h <= hi)
    log_pb = np.log(1.0 - p_good) - np.log(width) + np.where(inside, 0.0, np.log(_OUT_OF_RANGE))
    log_a = np.log(p_good) + log_pg_lik
    return 1.0 / (1.0 + np.exp(np.clip(log_pb - log_a, -700.0, 700.0)))


def _gauss_loglik(h, mu, var):
    return -0.5 * np.log(2.0 * np.pi * var) - (h - mu) ** 2 / (2.0 * var)


def probability_correct(left1, left2, h, n_others, n_good, n_total, *, method="gaussian", num_beta=5,
                        var_floor=1.0, new_feature=False, mean_shift=0.0):
    """``P(G | H)`` for matches (or hypothetical matches in gaps) with given left counts and inversions.

    Args:
        left1, left2, h: ``(M,)`` matches to the left in image 1 / image 2, and inversions ``H = H^l + H^r``.
        n_others: other matches (``n - 1`` for an existing match, ``n`` for a new feature in a gap).
        n_good: N_G of the model; n_total: n (for the prior ``P_G = N_G / n``).
        method: ``"gaussian"`` or ``"exact"`` (see module docstring).
        new_feature: gap of a new feature (others contain all N_G correct matches for both hypotheses) instead of
            an existing match (under G the others hold N_G - 1 correct ones, under B N_G).
        mean_shift: added to the mean of ``H | G`` ("gaussian" only; the order noise of :func:`order_noise`).
    """
    left1 = np.asarray(left1, dtype=np.int64).reshape(-1)
    left2 = np.asarray(left2, dtype=np.int64).reshape(-1)
    h = np.asarray(h, dtype=np.int64).reshape(-1)
    p_good = float(np.clip(n_good / max(n_total, 1), *_P_G_CLIP))
    g_under_g = float(n_good) if new_feature else max(float(n_good) - 1.0, 0.0)
    g_under_b = min(float(n_good), float(n_others))
    if method == "exact":
        if mean_shift:
            raise ValueError("mean_shift (order noise) is only defined for the gaussian model")
        nb = int(np.clip(round(n_others - g_under_g), 0, n_others))
        lik = _exact_lik_good(left1, left2, h, int(n_others), nb, _EXACT_NSD)
        with np.errstate(divide="ignore"):
            loglik = np.log(lik)
    elif method == "gaussian":
        mu, var = good_inversion_moments(left1, left2, n_others, g_under_g, num_beta, var_floor)
        loglik = _gauss_loglik(h, mu + mean_shift, var)
    else:
        raise ValueError(f"unknown probability method {method!r}")
    return _posterior(loglik, h, left1, n_others, g_under_b, p_good)


# --------------------------------------------------------------------------------------------------------------
# Local order noise among correct matches (our addition to Teng & Dong §III-C)
# --------------------------------------------------------------------------------------------------------------


class OrderNoise(NamedTuple):
    """Mean and variance (inversions, inversions^2) of ``H_G``, the inversions of a likely-correct match with the
    other likely-correct ones; added to the mean / variance of ``H | G`` (see :func:`order_noise`)."""

    mean: float
    var: float


def order_noise(sigma_w, prob_w, min_matches: int = 8) -> OrderNoise:
    """Local order noise of the likely-correct matches: mean and variance of their inversions among themselves.

    Talker's A1 says correct matches never invert each other, so ``P(H|G)`` only counts inversions with incorrect
    matches. Real pairs break A1 locally: depth discontinuities ("poles"), perspective, residual roll and
    keypoint noise swap nearby correct matches. Among the matches with ``P >= 1/2`` (taken as correct) we count,
    for each, the inversions it takes part in with the others (``H_G``); a correct *new* feature at its true gap
    meets the same disorder, so the search-range table adds ``mean(H_G)`` to the mean of ``H | G`` and
    ``var(H_G)`` to its variance (an addition to Teng & Dong §III-C; ``order_noise=False`` restores the paper).
    The estimate is conservative on the low side: matches whose disorder already made ``P < 1/2`` are left out.
    Returns ``OrderNoise(0, 0)`` with fewer than ``min_matches`` likely-correct matches.
    """
    good = np.asarray(prob_w) >= 0.5
    if int(good.sum()) < min_matches:
        return OrderNoise(0.0, 0.0)
    sub = np.asarray(sigma_w)[good]
    dense = np.argsort(np.argsort(sub, kind="stable"), kind="stable")
    hl, hr = inversions_per_match(dense)
    hg = (hl + hr).astype(np.float64)
    return OrderNoise(float(hg.mean()), float(hg.var()))
