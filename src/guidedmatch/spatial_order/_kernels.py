"""Numba kernels of the spatial-order model (all ``@njit(cache=True)`` code of :mod:`guidedmatch.spatial_order`).

Kept in one file so that Numba's on-disk cache (keyed on this file's path and modification time) is invalidated
whenever any kernel changes, including the ``inline="always"`` helpers the others inline. The pure-Python callers
live in :mod:`.ranks` (Kendall / Fenwick), :mod:`.window` (overlap search), :mod:`.probability` (exact likelihood)
and :mod:`.gap_table` (fused search-range table). Ranks are 0-based ints, Fenwick trees 1-based.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

# --------------------------------------------------------------------------------------------------------------
# Fenwick tree and Kendall inversions (Talker Eq. 1-2, §4.2)
# --------------------------------------------------------------------------------------------------------------


@njit(inline="always", cache=True)
def _fenwick_prefix(tree, q):  # pragma: no cover - numba
    """Sum of the Fenwick tree's counts at 1-based positions <= q."""
    s = 0
    t = q
    while t > 0:
        s += tree[t]
        t -= t & (-t)
    return s


@njit(inline="always", cache=True)
def _fenwick_add(tree, q, size):  # pragma: no cover - numba
    """Add one at 1-based position q of a Fenwick tree of length ``size``."""
    t = q
    while t < size:
        tree[t] += 1
        t += t & (-t)


@njit(inline="always", cache=True)
def _kendall_step(tree, v, lo, size, cnt, kk):  # pragma: no cover - numba
    """Insert value ``v`` (in ``[lo, lo + size - 1)``) after ``cnt`` earlier ones: returns ``(cnt + 1, kk + the
    earlier values larger than v)``."""
    q = v - lo + 1
    kk += cnt - _fenwick_prefix(tree, q)
    _fenwick_add(tree, q, size)
    return cnt + 1, kk


@njit(cache=True, nogil=True)
def _inversions_dense(r, nvals):  # pragma: no cover - numba
    """H^l, H^r for a sequence of dense ranks ``r`` (ties allowed, not inversions) via a Fenwick tree."""
    n = r.shape[0]
    tree = np.zeros(nvals + 1, dtype=np.int64)
    less_total = np.zeros(nvals + 1, dtype=np.int64)  # less_total[v] = #{j : r[j] < v}
    for j in range(n):
        less_total[r[j] + 1] += 1
    for v in range(1, nvals + 1):
        less_total[v] += less_total[v - 1]
    hl = np.empty(n, dtype=np.int64)
    hr = np.empty(n, dtype=np.int64)
    for i in range(n):
        v = r[i]
        # c_le = #{j < i : r[j] <= v}, c_lt = #{j < i : r[j] < v}
        hl[i] = i - _fenwick_prefix(tree, v + 1)
        hr[i] = less_total[v] - _fenwick_prefix(tree, v)
        _fenwick_add(tree, v + 1, nvals + 1)
    return hl, hr

# --------------------------------------------------------------------------------------------------------------
# Overlap window search (Talker §4.3)
# --------------------------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _sweep_kendall(seq, lo, hi, bounds, out_k, out_n):  # pragma: no cover - numba
    """For every start block a and end bound c > a: inversions / count among ``seq[bounds[a]:bounds[c]]``
    restricted to values in ``[lo, hi)``; an inversion is an earlier element with a larger value."""
    g = bounds.shape[0] - 1
    m = seq.shape[0]
    size = hi - lo + 1
    tree = np.zeros(size, dtype=np.int64)
    for a in range(g):
        tree[:] = 0
        cnt = 0
        kk = 0
        c = a + 1
        for p in range(bounds[a], m):
            v = seq[p]
            if v >= lo and v < hi:
                cnt, kk = _kendall_step(tree, v, lo, size, cnt, kk)
            if p + 1 == bounds[c]:
                out_k[a, c] = kk
                out_n[a, c] = cnt
                c += 1
                if c > g:
                    break


@njit(cache=True, nogil=True)
def _window_kendall(sigma, i1l, i1h, i2l, i2h):  # pragma: no cover - numba
    """(K, n) of the matches with image-1 rank in [i1l, i1h) and image-2 rank in [i2l, i2h)."""
    size = i2h - i2l + 1
    if size < 2:
        return 0, 0
    tree = np.zeros(size, dtype=np.int64)
    cnt = 0
    kk = 0
    for i in range(i1l, i1h):
        v = sigma[i]
        if v >= i2l and v < i2h:
            cnt, kk = _kendall_step(tree, v, i2l, size, cnt, kk)
    return kk, cnt


@njit(cache=True, nogil=True)
def _ng_scalar(kk, cnt):  # pragma: no cover - numba
    """N_G (Talker Eq. 8/10) of a window with kk inversions among cnt matches; 0 when cnt < 2."""
    if cnt < 2:
        return 0.0
    kh = 2.0 * kk / (cnt * (cnt - 1.0))
    if kh >= 0.5:
        return 0.0
    if kh == 0.0:
        return float(cnt)
    b = cnt / 3.0 - 0.5
    c = cnt * (cnt - 1.0) * (0.5 - kh)
    r = 3.0 * (-b + math.sqrt(b * b + (2.0 / 3.0) * c))
    return min(max(r, 0.0), float(cnt))


@njit(cache=True, nogil=True)
def _profile(seq, lo, hi, start, stop, step):  # pragma: no cover - numba
    """N_G after each position of a sweep over ``seq[start], seq[start+step], ...`` (stop exclusive), counting only
    values in [lo, hi). step=+1: appending (inversion = earlier larger value); step=-1: prepending (smaller)."""
    size = hi - lo + 1
    m = (stop - start) * step
    ng = np.zeros(max(m, 0))
    cn = np.zeros(max(m, 0), dtype=np.int64)
    if size < 2 or m <= 0:
        return ng, cn
    tree = np.zeros(size, dtype=np.int64)
    cnt = 0
    kk = 0
    p = start
    for t in range(m):
        v = seq[p]
        if v >= lo and v < hi:
            q = v - lo + 1
            le = _fenwick_prefix(tree, q)  # earlier values <= v
            if step > 0:
                kk += cnt - le
            else:
                kk += le
            _fenwick_add(tree, q, size)
            cnt += 1
        ng[t] = _ng_scalar(kk, cnt)
        cn[t] = cnt
        p += step
    return ng, cn


@njit(cache=True, nogil=True)
def _refine_window_nb(sigma, inv, w0, span, step, max_passes):  # pragma: no cover - numba
    """Coordinate ascent of N_G over the 4 window ends (see _refine_window)."""
    n = sigma.shape[0]
    w = w0.copy()
    kk, cnt = _window_kendall(sigma, w[0], w[1], w[2], w[3])
    best = _ng_scalar(kk, cnt)
    bcnt = cnt
    for _ in range(max_passes):
        changed = False
        for j in range(4):
            if j == 0:  # i1_lo: prepend image-1 ranks w1-1, w1-2, ..., 0
                ng, cn = _profile(sigma, w[2], w[3], w[1] - 1, -1, -1)
            elif j == 1:  # i1_hi: append image-1 ranks w0, ..., n-1
                ng, cn = _profile(sigma, w[2], w[3], w[0], n, 1)
            elif j == 2:
                ng, cn = _profile(inv, w[0], w[1], w[3] - 1, -1, -1)
            else:
                ng, cn = _profile(inv, w[0], w[1], w[2], n, 1)
            bt = -1
            for t in range(1, ng.shape[0]):  # windows of >= 2 ranks
                if ng[t] > best or (ng[t] == best and cn[t] > bcnt):
                    best = ng[t]
                    bcnt = cn[t]
                    bt = t
            if bt >= 0:
                if j == 0:
                    w[0] = w[1] - 1 - bt
                elif j == 1:
                    w[1] = w[0] + bt + 1
                elif j == 2:
                    w[2] = w[3] - 1 - bt
                else:
                    w[3] = w[2] + bt + 1
                changed = True
        for pair in range(2):  # joint shifts of (i1_lo, i2_lo) or (i1_hi, i2_hi)
            a = 0 if pair == 0 else 1
            b = a + 2
            bd = 0
            for d in range(-span, span + 1, step):
                if d == 0:
                    continue
                t0, t1, t2, t3 = w[0], w[1], w[2], w[3]
                if pair == 0:
                    t0 += d
                    t2 += d
                else:
                    t1 += d
                    t3 += d
                if t0 < 0 or t2 < 0 or t1 > n or t3 > n or t1 - t0 < 2 or t3 - t2 < 2:
                    continue
                kk, cnt = _window_kendall(sigma, t0, t1, t2, t3)
                g = _ng_scalar(kk, cnt)
                if g > best or (g == best and cnt > bcnt):
                    best = g
                    bcnt = cnt
                    bd = d
            if bd != 0:
                w[a] += bd
                w[b] += bd
                changed = True
        if not changed:
            break
    return w

# --------------------------------------------------------------------------------------------------------------
# Exact hypergeometric likelihood P(H | G) (Teng & Dong Eq. 7-9)
# --------------------------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _logfact_table(n):  # pragma: no cover - numba
    t = np.zeros(n + 2)
    for i in range(1, n + 2):
        t[i] = t[i - 1] + math.log(i)
    return t


@njit(cache=True, nogil=True)
def _log_hyp(lf, n, k, pop, succ):  # pragma: no cover - numba
    """log Hyp(n draws, k successes; population pop with succ successes); -inf outside the support."""
    if k < 0 or k > n or k > succ or n - k > pop - succ or n > pop or succ < 0:
        return -np.inf
    return (lf[succ] - lf[k] - lf[succ - k] + lf[pop - succ] - lf[n - k] - lf[pop - succ - n + k]
            - (lf[pop] - lf[n] - lf[pop - n]))


@njit(cache=True, nogil=True)
def _exact_lik_good(left1, left2, h, n_others, n_bad, nsd):  # pragma: no cover - numba
    """Exact P(H = h | G) for each entry (hypergeometric sums, Teng & Dong Eq. 7-9), beta within nsd sd."""
    m = left1.shape[0]
    lf = _logfact_table(n_others + 2)
    out = np.zeros(m)
    nb = n_bad
    p = nb / max(n_others, 1)
    for e in range(m):
        l1 = left1[e]
        l2 = left2[e]
        hh = h[e]
        sd1 = math.sqrt(max(l1 * p * (1 - p) * (n_others - l1) / max(n_others - 1, 1), 0.0))
        sd2 = math.sqrt(max(l2 * p * (1 - p) * (n_others - l2) / max(n_others - 1, 1), 0.0))
        lo1 = max(0, l1 - (n_others - nb), int(math.floor(l1 * p - nsd * sd1 - 1)))
        hi1 = min(l1, nb, int(math.ceil(l1 * p + nsd * sd1 + 1)))
        lo2 = max(0, l2 - (n_others - nb), int(math.floor(l2 * p - nsd * sd2 - 1)))
        hi2 = min(l2, nb, int(math.ceil(l2 * p + nsd * sd2 + 1)))
        tot = 0.0
        for b1 in range(lo1, hi1 + 1):
            lp1 = _log_hyp(lf, l1, b1, n_others, nb)
            if lp1 == -np.inf:
                continue
            for b2 in range(lo2, hi2 + 1):
                lp2 = _log_hyp(lf, l2, b2, n_others, nb)
                if lp2 == -np.inf:
                    continue
                s = 0.0
                for a in range(max(0, hh - b2), min(hh, b1) + 1):
                    la = _log_hyp(lf, b1, a, nb, nb - b2)
                    if la == -np.inf:
                        continue
                    lb = _log_hyp(lf, b2, hh - a, nb, nb - b1)
                    if lb == -np.inf:
                        continue
                    s += math.exp(la + lb)
                tot += math.exp(lp1 + lp2) * s
        out[e] = tot
    return out

# --------------------------------------------------------------------------------------------------------------
# Fused search-range (gap) table, Gaussian model (Teng & Dong §III-C)
# --------------------------------------------------------------------------------------------------------------


@njit(inline="always", cache=True)
def _gap_cell_moments(m1h, s1h, m2k, s2k, nb, fm, ca, cb, cc, var_floor):  # pragma: no cover - numba
    """Mean (without order-noise shift) and variance of H | G in gap cell (h, k) from the per-row constants
    ``fm, ca, cb, cc`` of :func:`_gap_kernel` (the expressions of ``probability._cell_moments`` expanded in m2, s2)."""
    mu = m1h + m2k * fm
    var_mu = s1h + ca * m2k + cb * s2k - mu * mu
    if var_mu < 0.0:
        var_mu = 0.0
    vh = cc * (nb * m2k - s2k)
    if vh < 0.0:
        vh = 0.0
    return mu, vh + var_mu + var_floor


@njit(cache=True, fastmath=True, nogil=True)
def _row_var_max(m1h, s1h, m2, s2, nb, fm, ca, cb, cc, var_floor):  # pragma: no cover - numba
    """max over k of the gap kernel's var(h, k) (vectorized; fast-math, so the caller adds a relative margin)."""
    v = var_floor
    for k in range(m2.shape[0]):
        v = max(v, _gap_cell_moments(m1h, s1h, m2[k], s2[k], nb, fm, ca, cb, cc, var_floor)[1])
    return v * (1.0 + 1e-6)


@njit(cache=True, nogil=True)
def _gap_kernel(sigma, m1, s1, m2, s2, blo, bhi, nb, log_pg, log_pb, log_odds_th, var_floor,
                log_out, mean_shift):  # pragma: no cover - numba
    """Fused pass over the (n+1)^2 gap table: C by incremental prefix sums, Gaussian P(H|G), threshold, runs."""
    n = sigma.shape[0]
    crow = np.zeros(n + 1, dtype=np.int64)
    gap_lo = np.full(n + 1, n + 1, dtype=np.int64)
    gap_hi = np.full(n + 1, -1, dtype=np.int64)
    count = np.zeros(n + 1, dtype=np.int64)
    ptr = np.zeros(n + 2, dtype=np.int64)
    cap = 2 * (n + 1)
    runs = np.empty((cap, 2), dtype=np.int64)
    nr = 0
    half_log_2pi = 0.5 * math.log(2.0 * math.pi)
    # skipping (exact): along a row, hv(k) = h + k - 2 C[h, k] moves by exactly +-1 per step and mu(k) by at most
    # |fm| * max|m2[k+1] - m2[k]|, so d = hv - mu is Lipschitz in k; a cell whose |d| exceeds the row's largest
    # admissible |d| (from an upper bound of var over the row) by x * L proves the next ceil(x) - 1 cells out too.
    dm2max = 0.0
    for k in range(n):
        dm2max = max(dm2max, abs(m2[k + 1] - m2[k]))
    for h in range(n + 1):
        if h > 0:
            s = sigma[h - 1]
            for k in range(s + 1, n + 1):
                crow[k] += 1
        width = bhi[h] - blo[h] + 1.0
        lpb_in = log_pb - math.log(width)
        lpb_out = lpb_in + log_out
        # a cell is surely out when the quadratic term alone exceeds this (uses var >= var_floor)
        bound = log_pg - half_log_2pi - 0.5 * math.log(var_floor) - lpb_out - log_odds_th
        if bound < 0.0:  # q >= 0 > bound: no cell of this row is admissible
            ptr[h + 1] = nr
            continue
        in_run = False
        # per-row constants of the cell moments (the expressions of _cell_moments expanded in m2[k], s2[k]):
        # mu = m1 + m2 - 2 m1 m2 / nb; E2 = s1 + A m2 + B s2; vh = C (nb m2 - s2)
        fm = ca = cb = cc = 0.0
        var_hi = var_floor
        lip = 1.0
        if nb >= 1e-9:
            inv_nb = 1.0 / nb
            fm = 1.0 - 2.0 * m1[h] * inv_nb
            ca = 2.0 * m1[h] - 4.0 * s1[h] * inv_nb
            cb = 1.0 - 4.0 * m1[h] * inv_nb + 4.0 * s1[h] * inv_nb * inv_nb
            cc = 2.0 * (nb * m1[h] - s1[h]) * inv_nb * inv_nb / (nb - 1.0) if nb > 1.0 else 0.0
            var_hi = _row_var_max(m1[h], s1[h], m2, s2, nb, fm, ca, cb, cc, var_floor)
            lip = 1.0 + abs(fm) * dm2max
        d_hi = math.sqrt(2.0 * var_hi * bound) * (1.0 + 1e-9) + 1e-9
        lip *= 1.0 + 1e-9
        k = 0
        while k <= n:
            hv = h + k - 2 * crow[k]
            if nb < 1e-9:
                mu = mean_shift
                var = var_floor
            else:
                mu, var = _gap_cell_moments(m1[h], s1[h], m2[k], s2[k], nb, fm, ca, cb, cc, var_floor)
                mu += mean_shift
            d = hv - mu
            # q = d^2 / (2 var) <= bound, tested without the division
            if d * d > 2.0 * var * bound:
                in_run = False
                ad = abs(d)
                if ad > d_hi:
                    k += int(math.ceil((ad - d_hi) / lip))  # the skipped cells are out as well
                else:
                    k += 1
                continue
            q = d * d / (2.0 * var)
            lpg = log_pg - half_log_2pi - 0.5 * math.log(var) - q
            lpb = lpb_in if (hv >= blo[h] and hv <= bhi[h]) else lpb_out
            if lpg - lpb >= log_odds_th:
                count[h] += 1
                if k < gap_lo[h]:
                    gap_lo[h] = k
                gap_hi[h] = k
                if not in_run:
                    if nr == cap:
                        cap *= 2
                        new = np.empty((cap, 2), dtype=np.int64)
                        for r in range(nr):  # element copy: a 2-D slice assignment costs ~4 s of first compile
                            new[r, 0] = runs[r, 0]  # (Numba's broadcast checks format shape strings)
                            new[r, 1] = runs[r, 1]
                        runs = new
                    runs[nr, 0] = k
                    nr += 1
                    in_run = True
                runs[nr - 1, 1] = k
            else:
                in_run = False
            k += 1
        ptr[h + 1] = nr
    return gap_lo, gap_hi, count, ptr, runs[:nr].copy()


# --------------------------------------------------------------------------------------------------------------
# One candidate window and its Gaussian model (model._window_fit; probability.probability_correct, "gaussian")
# --------------------------------------------------------------------------------------------------------------


@njit(inline="always", cache=True)
def _beta_moments_1(left, no, nb, nodes, weights):  # pragma: no cover - numba
    """probability._beta_moments for one ``left`` (``no >= 1``, ``0 <= nb <= no``), same operation order."""
    p = nb / no
    mean = left * p
    var = left * p * (1.0 - p) * (no - left) / max(no - 1.0, 1.0)
    sd = math.sqrt(max(var, 0.0))
    lo_s = max(0.0, left - (no - nb))
    hi_s = max(min(left, nb), lo_s)
    m = 0.0
    s = 0.0
    for t in range(nodes.shape[0]):
        b = min(max(mean + sd * nodes[t], lo_s), hi_s)
        m += b * weights[t]
        s += b * b * weights[t]
    return m, s


@njit(cache=True, nogil=True)
def _window_fit_gaussian(sigma, i1_lo, i1_hi, i2_lo, i2_hi, nodes, weights, var_floor, p_clip_lo, p_clip_hi,
                         out_of_range):  # pragma: no cover - numba
    """:func:`guidedmatch.spatial_order.model._window_fit` with the Gaussian ``P(H | G)`` in one pass without the
    GIL: the matches inside the window, their re-ranked sub-permutation, inversions, K_hat, N_G (Eq. 8) and
    ``P(G | H)`` per match (Eq. 12 via probability.probability_correct). Returns ``nw = 0`` arrays when fewer than
    2 matches are inside. Same formulas and operation order as the NumPy functions (results agree to rounding)."""
    n = sigma.shape[0]
    nw = 0
    for i in range(i1_lo, i1_hi):
        if sigma[i] >= i2_lo and sigma[i] < i2_hi:
            nw += 1
    ranks1 = np.empty(nw, np.int64)
    ranks2 = np.empty(nw, np.int64)
    k = 0
    for i in range(i1_lo, i1_hi):
        if sigma[i] >= i2_lo and sigma[i] < i2_hi:
            ranks1[k] = i
            ranks2[k] = sigma[i]
            k += 1
    if nw < 2:
        z = np.zeros(0, np.int64)
        return ranks1, ranks2, z, z, z, 0.0, 0.0, np.zeros(0)
    # dense rank of each image-2 rank among the selected ones (the cumsum of a 0/1 mark, minus 1)
    dense = np.full(n, -1, np.int64)
    for t in range(nw):
        dense[ranks2[t]] = 0
    c = 0
    for v in range(n):
        if dense[v] == 0:
            dense[v] = c
            c += 1
    sigma_w = np.empty(nw, np.int64)
    for t in range(nw):
        sigma_w[t] = dense[ranks2[t]]
    hl, hr = _inversions_dense(sigma_w, nw)
    kk = 0
    for t in range(nw):
        kk += hl[t]
    k_hat = 2.0 * float(kk) / (nw * (nw - 1.0))
    n_good = _ng_scalar(kk, nw)
    # probability_correct(arange(nw), sigma_w, hl + hr, nw - 1, n_good, nw, method="gaussian")
    n_others = nw - 1.0
    p_good = min(max(n_good / max(float(nw), 1.0), p_clip_lo), p_clip_hi)
    g_under_g = max(n_good - 1.0, 0.0)
    g_under_b = min(n_good, n_others)
    no = max(n_others, 1.0)
    nbc = max(n_others - g_under_g, 0.0)  # good_inversion_moments' nb, as _cell_moments uses it
    nb = min(nbc, no)                     # ... and as _beta_moments clips it
    gb = min(max(g_under_b, 0.0), no)
    bb = no - gb
    log_pb0 = math.log(1.0 - p_good)
    log_pg = math.log(p_good)
    log_out = math.log(out_of_range)
    prob = np.empty(nw)
    for t in range(nw):
        h = float(hl[t] + hr[t])
        m1, s1 = _beta_moments_1(float(t), no, nb, nodes, weights)
        m2, s2 = _beta_moments_1(float(sigma_w[t]), no, nb, nodes, weights)
        if nbc < 1e-9:
            mu = 0.0
            var = var_floor
        else:
            mu = m1 + m2 - 2.0 * m1 * m2 / nbc
            e2 = s1 + s2 + 2.0 * m1 * m2 - 4.0 * (s1 * m2 + m1 * s2) / nbc + 4.0 * s1 * s2 / (nbc * nbc)
            var_mu = max(e2 - mu * mu, 0.0)
            vh = 2.0 * (nbc * m1 - s1) * (nbc * m2 - s2) / (nbc * nbc * (nbc - 1.0)) if nbc > 1.0 else 0.0
            var = max(vh, 0.0) + var_mu + var_floor
        loglik = -0.5 * math.log(2.0 * math.pi * var) - (h - mu) ** 2 / (2.0 * var)
        # uniform P(H | B) between probability.bad_inversion_range's bounds
        x = min(max(float(t) / no, 0.0), 1.0)
        hx = 2.0 * bb * x * (1.0 - x)
        h0 = no * x
        h1 = no * (1.0 - x)
        lo = max(min(min(hx, h0), h1) - 2.0 * math.sqrt(2.0 * bb * x * (1.0 - x)) - 1.0, 0.0)
        hi = max(h0, h1)
        log_pb = log_pb0 - math.log(hi - lo + 1.0) + (0.0 if (h >= lo and h <= hi) else log_out)
        log_a = log_pg + loglik
        prob[t] = 1.0 / (1.0 + math.exp(min(max(log_pb - log_a, -700.0), 700.0)))
    return ranks1, ranks2, sigma_w, hl, hr, k_hat, n_good, prob
