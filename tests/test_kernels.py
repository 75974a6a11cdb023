"""Unit tests of the Numba kernels (``guidedmatch.kernels``) and ``bruteforce.DenseKnn2``.

Every result is compared with a slow, obviously correct plain-NumPy reference written here (exact integer or
float64 arithmetic), never with recorded outputs of the code under test.
"""
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from threadpoolctl import threadpool_info

from guidedmatch import kernel_threads, kernels
from guidedmatch.bruteforce import DenseKnn2, knn2
from guidedmatch.exact import l2

INF32 = np.float32(np.inf)

#: Band membership. For integer descriptors (uint8 L2, binary) the kernel is compiled without fast-math, so the plain
#: float64 expression |a*x + b*y + c| <= band decides exactly, also for points built on the band edge. For float
#: descriptors it needs fast-math (the L2 sum vectorizes only with 'reassoc'), and LLVM then contracts the band
#: distance into fma(a, x, fma(b, y, c)), which can differ by an ulp: e.g. a, b, c = -0.41712332493858084,
#: 0.9088498950828916, 376.47774069425947, band = 1.0, x, y = 97.04889326126471, -368.59374190163487 gives exactly
#: 1.0 in plain float64 but 1.0000000000000182 contracted. There, points within FLOAT_EDGE_TOL px of the band edge
#: may be either inside or outside; every other point must be classified exactly.
FLOAT_EDGE_TOL = 1e-9


# --------------------------------------------------------------------------- references
def ref_dist(kind, qd, d2):
    """Exact distances (float64) of one query descriptor row to every row of ``d2``."""
    if kind == "bin":
        return np.unpackbits(d2 ^ qd[None, :], axis=1).sum(axis=1).astype(np.float64)
    if kind == "u8":
        return ((d2.astype(np.int64) - qd.astype(np.int64)) ** 2).sum(axis=1).astype(np.float64)
    return ((d2.astype(np.float64) - qd.astype(np.float64)) ** 2).sum(axis=1)


def ref_top2(cand, dist):
    """The first two of ``cand`` sorted by (distance, index); -1 where missing."""
    cand = np.asarray(cand, np.int64)
    order = cand[np.lexsort((cand, dist[cand]))]
    return (int(order[0]) if len(order) > 0 else -1), (int(order[1]) if len(order) > 1 else -1)


def ref_region(pts2, line, use_band, band, lo, hi, edge_tol=None):
    """Reference candidate predicate -> (sure, ambiguous) boolean masks over image-2 points (ambiguous: within
    ``edge_tol`` of the band edge, for the fast-math float kernel)."""
    x, y = pts2[:, 0], pts2[:, 1]
    inx = (lo <= x) & (x <= hi)
    none = np.zeros(len(pts2), bool)
    if not use_band:
        return inx, none
    a, b, c = (float(v) for v in line)
    if a == 0.0 and b == 0.0:  # undefined epipolar line: no candidates at all
        return none, none
    val = np.abs(a * x + b * y + c)
    if edge_tol is None:
        return inx & (val <= band), none
    amb = inx & (np.abs(val - band) <= edge_tol)
    return inx & (val <= band) & ~amb, amb


def check_guided(res, n2, dists, sure, amb):
    """Compare the kernel's ``(i1, d1, i2, d2, ncand)`` with the reference, query by query.

    Points in ``amb`` may have been counted or not (the references here pass none: membership is exact); the result
    must equal the reference on ``sure`` plus *some* subset of them: the ambiguous points the kernel returned are in
    that subset, and any further ones it counted must rank after its second best.
    """
    i1, d1, i2, d2, nc = res
    assert i1.dtype == np.int64 and i2.dtype == np.int64 and nc.dtype == np.int64
    assert d1.dtype == np.float32 and d2.dtype == np.float32
    for q in range(len(nc)):
        S = np.flatnonzero(sure[q])
        A = np.flatnonzero(amb[q])
        dist = dists[q]
        got = (int(i1[q]), int(i2[q]))
        assert all(-1 <= j < n2 for j in got), (q, got)
        B = [j for j in got if j >= 0 and amb[q][j]]
        k = int(nc[q]) - len(S)
        assert len(B) <= k <= len(A), (q, int(nc[q]), len(S), len(A), got)
        e1, e2 = ref_top2(np.concatenate([S, np.array(B, np.int64)]), dist)
        assert got == (e1, e2), (q, got, (e1, e2))
        assert d1[q] == (np.float32(dist[e1]) if e1 >= 0 else INF32), (q, d1[q])
        assert d2[q] == (np.float32(dist[e2]) if e2 >= 0 else INF32), (q, d2[q])
        if k > len(B):  # counted-but-not-returned ambiguous points must rank after the second best
            assert e2 >= 0
            later = [j for j in A if j not in B and (dist[j], j) > (dist[e2], e2)]
            assert len(later) >= k - len(B), (q, k, B, later)


def make_desc(kind, rng, n, dim, small):
    hi = 4 if small else 256  # small value ranges force many distance ties
    if kind == "f32":
        return rng.integers(0, hi, (n, dim)).astype(np.float32)
    return rng.integers(0, hi, (n, dim), dtype=np.uint8)


def kernel_desc(kind, d):
    return kernels.pack_bits_u64(d) if kind == "bin" else d


def strips(pts2, width, dummy_rows):
    cols = kernels.build_strips(pts2, width, axis=0)
    rows = kernels.build_strips(np.zeros((0, 2)), 1.0) if dummy_rows else kernels.build_strips(pts2, width, axis=1)
    return cols, rows


def run_and_check(queries, desc1, desc2, kind, pts2, lines, use_band, band, xlo, xhi, cols, rows):
    res = kernels.guided_top2(queries, kernel_desc(kind, desc1), kernel_desc(kind, desc2), lines, use_band, band,
                              xlo, xhi, cols, rows)
    dists = [ref_dist(kind, desc1[qi], desc2) for qi in queries]
    tol = FLOAT_EDGE_TOL if kind == "f32" else None
    regions = [ref_region(pts2, lines[q], use_band, band, xlo[q], xhi[q], tol) for q in range(len(queries))]
    check_guided(res, len(pts2), dists, [r[0] for r in regions], [r[1] for r in regions])
    return res, regions


# --------------------------------------------------------------------------- guided_top2
S45 = float(np.sqrt(0.5))
NORMALS = {"horizontal": (0.0, 1.0), "vertical": (1.0, 0.0), "diag45": (S45, S45), "diag135": (-S45, S45)}


@st.composite
def guided_cases(draw):
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    layout = draw(st.sampled_from(["small", "large", "grid", "duplicates"]))
    n = draw(st.integers(0, 260))
    width = draw(st.one_of(st.sampled_from([1.0, 2.5, 7.0, 24.0, 100.0]), st.floats(1.0, 100.0)))
    if layout == "small":  # span of ~20 px, half of them on a 0.5 px lattice
        base = rng.uniform(0, 20, (n, 2))
        base[: n // 2] = np.round(base[: n // 2] * 2) / 2
    elif layout == "large":  # span of ~5000 px
        base = rng.uniform(-50, 5000, (n, 2))
    elif layout == "grid":  # exactly on strip (and often cell) boundaries
        base = rng.integers(0, 12, (n, 2)) * width + rng.integers(-5, 5, 2)
    else:  # many duplicated positions
        distinct = np.round(rng.uniform(0, 300, (max(1, n // 8), 2)))
        base = distinct[rng.integers(0, len(distinct), n)]
    lo_b = base.min(axis=0) if n else np.zeros(2)
    hi_b = base.max(axis=0) if n else np.full(2, 100.0)
    span = float(max(hi_b - lo_b)) + 1.0

    nq = draw(st.integers(0, 10))
    band = draw(st.one_of(st.sampled_from([0.0, 1.0, 2.5, 20.0]), st.floats(0.0, 20.0)))
    use_band = draw(st.booleans())
    lines, xlo, xhi, edge = [], [], [], []
    for _ in range(nq):
        kind = draw(st.sampled_from(["horizontal", "vertical", "diag45", "diag135", "random", "undefined"]))
        # the line passes through a feature (exact hits) or through a random position
        p = base[rng.integers(n)] if n and rng.random() < 0.5 else rng.uniform(lo_b - 5, hi_b + 5)
        if kind == "undefined":
            lines.append((0.0, 0.0, float(rng.choice([np.inf, 0.0, 3.0]))))
        else:
            if kind == "random":
                phi = rng.uniform(0, 2 * np.pi)
                a, b = float(np.cos(phi)), float(np.sin(phi))
            else:
                a, b = NORMALS[kind]
                if rng.random() < 0.5:
                    a, b = -a, -b
            lines.append((a, b, -(a * p[0] + b * p[1])))
            if rng.random() < 0.6:  # points built on the band edge |a x + b y + c| == band (up to rounding)
                t = rng.uniform(-span, span, int(rng.integers(1, 6)))
                if rng.random() < 0.5:
                    t = np.round(t)
                s = rng.choice([-1.0, 1.0], len(t))
                edge.append(np.stack([p[0] - b * t + s * band * a, p[1] + a * t + s * band * b], axis=1))
        rk = draw(st.sampled_from(["all", "lo_only", "hi_only", "finite", "at_points", "single", "empty"]))
        u, v = sorted(rng.uniform(lo_b[0] - 5, hi_b[0] + 5, 2))
        if rk in ("at_points", "single", "empty") and n:  # bounds exactly on feature x coordinates
            u, v = sorted(base[rng.integers(0, n, 2), 0])
        if rk == "single":
            v = u
        lo, hi = {"all": (-np.inf, np.inf), "lo_only": (u, np.inf), "hi_only": (-np.inf, v),
                  "empty": (v + 1.0, v)}.get(rk, (u, v))
        xlo.append(lo)
        xhi.append(hi)
    pts2 = np.concatenate([base] + edge)[:300] if edge else base
    pts2 = pts2[rng.permutation(len(pts2))]

    dkind = draw(st.sampled_from(["f32", "u8", "bin"]))
    dim = draw(st.sampled_from({"f32": [1, 3, 8], "u8": [4, 16], "bin": [1, 8, 32, 61]}[dkind]))
    small = draw(st.booleans())
    n1 = nq + int(rng.integers(0, 4))
    desc1 = make_desc(dkind, rng, n1, dim, small)
    desc2 = make_desc(dkind, rng, len(pts2), dim, small)
    queries = rng.integers(0, max(n1, 1), nq)
    lines = np.array(lines, np.float64).reshape(-1, 3)
    needs_rows = use_band and bool(np.any(np.abs(lines[:, 0]) > np.abs(lines[:, 1])))
    dummy_rows = not needs_rows and draw(st.booleans())
    return dict(queries=queries, desc1=desc1, desc2=desc2, kind=dkind, pts2=pts2, lines=lines, use_band=use_band,
                band=band, xlo=np.array(xlo, np.float64), xhi=np.array(xhi, np.float64), width=width,
                dummy_rows=dummy_rows)


@settings(max_examples=200, deadline=None)
@given(case=guided_cases())
def test_guided_top2_matches_reference(case):
    c = case
    cols, rows = strips(c["pts2"], c["width"], c["dummy_rows"])
    run_and_check(c["queries"], c["desc1"], c["desc2"], c["kind"], c["pts2"], c["lines"], c["use_band"], c["band"],
                  c["xlo"], c["xhi"], cols, rows)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_axis_aligned_band_edges_are_inclusive_exactly(sign):
    # with a, b in {0, +-1} and integer coordinates every evaluation order is exact: no tolerance needed
    g = np.arange(0, 31, dtype=np.float64)
    pts2 = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)  # lattice on strip boundaries for width 1, 5 and 6
    lines = sign * np.array([[0.0, 1.0, -10.0], [1.0, 0.0, -17.0], [0.0, 1.0, -30.0], [1.0, 0.0, 0.0]])
    xlo = np.array([3.0, -np.inf, 0.0, 0.0])
    xhi = np.array([12.0, np.inf, 30.0, 2.0])
    desc = np.zeros((len(pts2), 1), np.float32)
    for width in (1.0, 5.0, 6.0):
        cols, rows = strips(pts2, width, False)
        for band in (0.0, 3.0):
            res = kernels.guided_top2(np.zeros(4, np.int64), desc[:1], desc, lines, True, band, xlo, xhi, cols, rows)
            x, y = pts2[:, 0], pts2[:, 1]
            w = 2 * band + 1
            expect = [(np.abs(y - 10) <= band) & (x >= 3) & (x <= 12),
                      np.abs(x - 17) <= band, np.abs(y - 30) <= band, (np.abs(x) <= band) & (x <= 2)]
            np.testing.assert_array_equal(res[4], [10 * w, 31 * w, 31 * (band + 1), 31 * min(band + 1, 3)])
            np.testing.assert_array_equal(res[4], [e.sum() for e in expect])
            # all descriptors equal: best two are the two lowest candidate indices
            np.testing.assert_array_equal(res[0], [np.flatnonzero(e)[0] for e in expect])
            np.testing.assert_array_equal(res[2], [np.flatnonzero(e)[1] for e in expect])


def test_undefined_lines_give_no_candidates_with_band_and_all_without():
    rng = np.random.default_rng(1)
    pts2 = rng.uniform(0, 100, (50, 2))
    desc2 = rng.integers(0, 4, (50, 3)).astype(np.float32)
    cols, rows = strips(pts2, 10.0, False)
    lines = np.array([[0.0, 0.0, np.inf], [0.0, 0.0, 0.0], [-0.0, 0.0, -2.0]])
    inf = np.full(3, np.inf)
    res = kernels.guided_top2(np.zeros(3, np.int64), desc2, desc2, lines, True, 5.0, -inf, inf, cols, rows)
    np.testing.assert_array_equal(res[4], 0)
    np.testing.assert_array_equal(res[0], -1)
    assert np.all(np.isinf(res[1])) and np.all(np.isinf(res[3]))
    res = kernels.guided_top2(np.zeros(3, np.int64), desc2, desc2, lines, False, 5.0, -inf, inf, cols, rows)
    np.testing.assert_array_equal(res[4], 50)


def test_guided_top2_arbitrary_float_descriptors():
    # non-integer floats: the kernel's fast-math sum may round differently, so compare within float32 rounding
    rng = np.random.default_rng(2)
    pts2 = rng.uniform(0, 640, (300, 2))
    desc1 = rng.normal(size=(40, 32)).astype(np.float32)
    desc2 = rng.normal(size=(300, 32)).astype(np.float32)
    phi = rng.uniform(0, np.pi, 40)
    p = rng.uniform(0, 640, (40, 2))
    lines = np.stack([np.cos(phi), np.sin(phi), -(np.cos(phi) * p[:, 0] + np.sin(phi) * p[:, 1])], 1)
    xlo, xhi = np.full(40, 100.0), np.full(40, 500.0)
    cols, rows = strips(pts2, 24.0, False)
    i1, d1, i2, d2, nc = kernels.guided_top2(np.arange(40), desc1, desc2, lines, True, 40.0, xlo, xhi, cols, rows)
    for q in range(40):
        sure, amb = ref_region(pts2, lines[q], True, 40.0, xlo[q], xhi[q], FLOAT_EDGE_TOL)
        assert not amb.any()
        cand = np.flatnonzero(sure)
        assert nc[q] == len(cand)
        dist = ref_dist("f32", desc1[q], desc2)
        s = np.sort(dist[cand])
        if len(cand) >= 2:
            assert i1[q] in cand and i2[q] in cand and i1[q] != i2[q]
            np.testing.assert_allclose([d1[q], d2[q]], s[:2], rtol=1e-5)
            np.testing.assert_allclose([dist[i1[q]], dist[i2[q]]], s[:2], rtol=1e-5)


def test_near_vertical_line_without_row_strips_raises():
    pts2 = np.array([[0.0, 0.0], [10.0, 5.0]])
    desc = np.zeros((2, 4), np.float32)
    cols, dummy = strips(pts2, 5.0, True)
    lines = np.array([[0.0, 1.0, -1.0], [0.8, 0.6, -3.0]])  # the second is closer to vertical: |a| > |b|
    args = (np.zeros(2, np.int64), desc, desc, lines, True, 2.0, np.full(2, -np.inf), np.full(2, np.inf), cols)
    with pytest.raises(ValueError, match="row strips"):
        kernels.guided_top2(*args, dummy)
    kernels.guided_top2(*args, kernels.build_strips(pts2, 5.0, axis=1))  # fine with the row strips
    # without band the row strips are never used
    a = args[:4] + (False,) + args[5:]
    np.testing.assert_array_equal(kernels.guided_top2(*a, dummy)[4], [2, 2])


@pytest.mark.parametrize("which", ["lines", "xlo", "xhi"])
def test_mismatched_lengths_raise(which):
    pts2 = np.array([[0.0, 0.0], [10.0, 5.0]])
    desc = np.zeros((2, 4), np.float32)
    cols, rows = strips(pts2, 5.0, False)
    kw = dict(lines=np.tile([0.0, 1.0, 0.0], (3, 1)), xlo=np.zeros(3), xhi=np.ones(3))
    kw[which] = kw[which][:2]
    with pytest.raises(ValueError, match="same length"):
        kernels.guided_top2(np.zeros(3, np.int64), desc, desc, kw["lines"], True, 1.0, kw["xlo"], kw["xhi"],
                            cols, rows)


def test_zero_queries_return_empty_arrays():
    pts2 = np.array([[0.0, 0.0], [10.0, 5.0]])
    desc = np.zeros((2, 4), np.float32)
    cols, rows = strips(pts2, 5.0, True)
    res = kernels.guided_top2(np.zeros(0, np.int64), desc, desc, np.zeros((0, 3)), True, 1.0, np.zeros(0),
                              np.zeros(0), cols, rows)
    assert len(res) == 5
    for arr, dt in zip(res, (np.int64, np.float32, np.int64, np.float32, np.int64)):
        assert arr.shape == (0,) and arr.dtype == dt


def test_parallel_path_equals_serial_path_and_reference():
    rng = np.random.default_rng(7)
    nq = 2100
    assert nq >= kernels.PARALLEL_MIN_QUERIES > nq // 2
    pts2 = np.round(rng.uniform(0, 800, (300, 2)))
    desc1 = rng.integers(0, 256, (nq, 16), dtype=np.uint8)
    desc2 = rng.integers(0, 256, (300, 16), dtype=np.uint8)
    phi = rng.uniform(0, 2 * np.pi, nq)
    p = rng.uniform(0, 800, (nq, 2))
    lines = np.stack([np.cos(phi), np.sin(phi), -(np.cos(phi) * p[:, 0] + np.sin(phi) * p[:, 1])], 1)
    lines[::97] = (0.0, 0.0, np.inf)
    xlo = np.where(rng.random(nq) < 0.3, -np.inf, rng.uniform(-10, 800, nq))
    xhi = np.where(rng.random(nq) < 0.3, np.inf, xlo + rng.uniform(-50, 400, nq))
    queries = rng.permutation(nq)
    cols, rows = strips(pts2, 24.0, False)
    par = kernels.guided_top2(queries, desc1, desc2, lines, True, 12.0, xlo, xhi, cols, rows)
    h = nq // 2
    ser = [kernels.guided_top2(queries[s], desc1, desc2, lines[s], True, 12.0, xlo[s], xhi[s], cols, rows)
           for s in (slice(0, h), slice(h, nq))]
    for k in range(5):
        np.testing.assert_array_equal(par[k], np.concatenate([ser[0][k], ser[1][k]]))
    # and both equal the reference (vectorised over all queries)
    x, y = pts2[:, 0], pts2[:, 1]
    val = np.abs(lines[:, :1] * x + lines[:, 1:2] * y + lines[:, 2:])
    inx = (xlo[:, None] <= x) & (x <= xhi[:, None])
    defined = (lines[:, 0] != 0) | (lines[:, 1] != 0)
    sure = inx & (val <= 12.0) & defined[:, None]
    amb = np.zeros_like(sure)
    dist = ((desc1[queries][:, None, :].astype(np.int64) - desc2[None].astype(np.int64)) ** 2).sum(-1)
    check_guided(par, len(pts2), dist.astype(np.float64), sure, amb)
    assert par[4].sum() > 0 and (par[4] == 0).any()


# --------------------------------------------------------------------------- build_strips / counting_order
@st.composite
def point_sets(draw):
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n = draw(st.integers(0, 300))
    layout = draw(st.sampled_from(["uniform", "grid", "duplicates", "huge", "line"]))
    width = draw(st.one_of(st.sampled_from([1.0, 6.0, 24.0, 100.0]), st.floats(1.0, 100.0)))
    if layout == "uniform":
        pts = rng.uniform(-100, 5000, (n, 2))
    elif layout == "grid":
        pts = rng.integers(0, 20, (n, 2)) * width
    elif layout == "duplicates":
        pts = np.round(rng.uniform(0, 50, (max(1, n // 10), 2)))[rng.integers(0, max(1, n // 10), n)]
    elif layout == "huge":  # coordinates spread over 1e7 px on one or both axes
        pts = rng.uniform(0, 1e7, (n, 2))
        if rng.random() < 0.5:
            pts[:, int(rng.integers(2))] = rng.uniform(0, float(rng.choice([10, 1000, 1e5])), n)
    else:  # all on one vertical or horizontal line
        pts = rng.uniform(0, 1000, (n, 2))
        pts[:, int(rng.integers(2))] = 7.0
    cell = draw(st.one_of(st.none(), st.floats(0.5, 50.0)))
    return pts, width, draw(st.sampled_from([0, 1])), cell


@settings(max_examples=150, deadline=None)
@given(case=point_sets())
def test_build_strips_invariants(case):
    pts, width, axis, cell = case
    n = len(pts)
    u0, ns, w, k0, nk, h, offsets, items, ps = kernels.build_strips(pts, width, axis=axis, cell=cell)
    assert ns >= 1 and nk >= 1 and w >= width and h >= (cell or width / 6.0)
    assert offsets.dtype == np.int64 and items.dtype == np.int64
    assert len(offsets) == ns * nk + 1 and offsets[0] == 0 and offsets[-1] == n
    assert np.all(np.diff(offsets) >= 0)
    np.testing.assert_array_equal(np.sort(items), np.arange(n))  # every point exactly once
    assert ps.shape == (n, 2) and ps.dtype == np.float64 and ps.flags.c_contiguous
    np.testing.assert_array_equal(ps, pts[items].reshape(-1, 2))
    # the points of strip s, cell k really lie there (the last strip / cell is closed)
    cell_of = np.repeat(np.arange(ns * nk), np.diff(offsets))
    s, k = cell_of // nk, cell_of % nk
    # up to float rounding of the boundaries (e.g. v = 8.75 in cell 29 of height fl(1.75 / 6): exactly below
    # 30 * h, but fl(30 * h) == 8.75); the kernel pads every scan window by a relative 1e-7, far more than this
    u, v = ps[:, axis], ps[:, 1 - axis]
    tu = 1e-12 * (1.0 + abs(u0) + ns * w)
    tv = 1e-12 * (1.0 + abs(k0) + nk * h)
    assert np.all(u >= u0 + s * w - tu)
    assert np.all(np.where(s < ns - 1, u < u0 + (s + 1) * w + tu, u <= u0 + ns * w + tu))
    assert np.all(v >= k0 + k * h - tv)
    assert np.all(np.where(k < nk - 1, v < k0 + (k + 1) * h + tv, v <= k0 + nk * h + tv))
    # the strip of every point is also the one the guided kernel computes for an x-range starting at it
    sid = np.minimum(((u - u0) // w).astype(np.int64), ns - 1)
    np.testing.assert_array_equal(sid, s)
    # the table stays O(N): strips * cells <= 4 N + 4096
    assert ns * nk <= 4 * n + 4096
    assert len(offsets) == ns * nk + 1


def _build_strips_numpy(pts, width, axis=0, cell=None):
    """The NumPy formulation build_strips had before its nogil kernel (the reference it must reproduce exactly)."""
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    width = float(width)
    cell = float(cell) if cell else width / 6.0
    n = len(pts)
    u, v = pts[:, axis], pts[:, 1 - axis]
    u0, k0 = float(u.min()), float(v.min())
    su, sv = float(u.max()) - u0, float(v.max()) - k0
    budget = 4 * n + 4096
    width = max(width, su / (budget // 4) * (1.0 + 1e-12))
    ns = int(su // width) + 1
    kmax = budget // ns
    cell = max(cell, sv / (kmax - 1) * (1.0 + 1e-12))
    nk = int(sv // cell) + 1
    sid = np.minimum(((u - u0) // width).astype(np.int64), ns - 1)
    kid = np.minimum(((v - k0) // cell).astype(np.int64), nk - 1)
    key = sid * nk + kid
    items = np.argsort(key, kind="stable")
    offsets = np.concatenate([[0], np.cumsum(np.bincount(key, minlength=ns * nk))])
    return u0, ns, width, k0, nk, cell, offsets, items, pts[items]


@settings(max_examples=150, deadline=None)
@given(case=point_sets())
def test_build_strips_kernel_equals_the_numpy_formulation(case):
    pts, width, axis, cell = case
    if len(pts) == 0:
        return
    got = kernels.build_strips(pts, width, axis=axis, cell=cell)
    ref = _build_strips_numpy(pts, width, axis=axis, cell=cell)
    assert tuple(got[:6]) == tuple(ref[:6])
    for a, b in zip(got[6:], ref[6:]):
        np.testing.assert_array_equal(a, b)


def test_build_strips_table_bounded_for_1e7_spread():
    rng = np.random.default_rng(3)
    for n in (1, 2, 50, 300):
        pts = rng.uniform(0, 1e7, (n, 2))
        for axis in (0, 1):
            S = kernels.build_strips(pts, 1.0, axis=axis)
            assert len(S[6]) <= 4 * n + 4096 + 1
            assert S[1] * S[2] >= pts[:, axis].max() - pts[:, axis].min()


def test_build_strips_table_within_single_budget():
    # strips and cells are sized together: a long thin spread used to give 4104 strips x 2 cells
    pts = np.array([[0.0, 0.0], [1e7, 50.0]])
    for axis in (0, 1):
        S = kernels.build_strips(pts, 1.0, axis=axis)
        assert len(S[6]) <= 4 * len(pts) + 4096 + 1


def test_build_strips_empty():
    u0, ns, w, k0, nk, h, offsets, items, ps = kernels.build_strips(np.zeros((0, 2)), 1.0)
    assert ns == 1 and nk == 1
    np.testing.assert_array_equal(offsets, [0, 0])
    assert items.shape == (0,) and ps.shape == (0, 2)


@settings(max_examples=100, deadline=None)
@given(key=st.lists(st.integers(0, 40), max_size=200), extra=st.integers(0, 5))
def test_counting_order_is_stable_argsort(key, extra):
    key = np.array(key, np.int64)
    nbins = (int(key.max()) + 1 if len(key) else 0) + extra
    order, offsets = kernels.counting_order(key, nbins)
    np.testing.assert_array_equal(order, np.argsort(key, kind="stable"))
    expect = np.concatenate([[0], np.cumsum(np.bincount(key, minlength=nbins))])
    np.testing.assert_array_equal(offsets, expect)
    assert len(offsets) == nbins + 1


@settings(max_examples=150, deadline=None)
@given(a=st.lists(st.integers(-5, 40), max_size=120), b=st.lists(st.integers(-5, 40), max_size=120))
def test_sorted_join_is_searchsorted_left_and_right(a, b):
    from guidedmatch.strip_index import sorted_join

    a, b = np.sort(np.array(a, np.int64)), np.sort(np.array(b, np.int64))
    lo, cnt = sorted_join(a, b)
    np.testing.assert_array_equal(lo, np.searchsorted(b, a, "left"))
    np.testing.assert_array_equal(cnt, np.searchsorted(b, a, "right") - np.searchsorted(b, a, "left"))


# --------------------------------------------------------------------------- GEMM top-k
def gemm_block(r, c, ties, seed):
    """A GEMM block ``dot (r, c)`` with column and row squared norms; ``ties``: small integers (many equal
    distances, and clamped (zero) ones)."""
    rng = np.random.default_rng(seed)
    if ties:
        dot = rng.integers(-3, 4, (r, c)).astype(np.float32)
        nn2 = rng.integers(0, 7, c).astype(np.float32)
        qn = rng.integers(0, 7, r).astype(np.float32)
    else:
        dot = (rng.normal(size=(r, c)) * 10).astype(np.float32)
        nn2 = rng.uniform(0, 50, c).astype(np.float32)
        qn = rng.uniform(0, 50, r).astype(np.float32)
    return dot, nn2, qn


# --------------------------------------------------------------------------- topk_gemm (IVF coarse step)
@settings(max_examples=80, deadline=None)
@given(r=st.integers(0, 12), c=st.sampled_from([0, 1, 5, 15, 16, 17, 40, 181, 300]), k=st.integers(1, 6), ties=st.booleans(),
       seed=st.integers(0, 2**32 - 1))
def test_topk_gemm_serial_bit_identical_to_numpy(r, c, k, ties, seed):
    dot, nn2, qn = gemm_block(r, c, ties, seed)
    ref = np.maximum((qn[:, None] + nn2[None, :]) + dot * np.float32(-2.0), 0)   # faiss's order
    idx, dist = kernels.topk_gemm_serial(dot, nn2, qn, k)
    assert idx.shape == dist.shape == (r, k) and idx.dtype == np.int64 and dist.dtype == np.float32
    for row in range(r):
        order = np.lexsort((np.arange(c), ref[row]))[:k]      # by distance, then the lower index
        want_i = np.full(k, -1)
        want_i[:len(order)] = order
        want_d = np.full(k, np.inf, np.float32)
        want_d[:len(order)] = ref[row, order]
        assert idx[row].tolist() == want_i.tolist()
        np.testing.assert_array_equal(dist[row].view(np.uint32), want_d.view(np.uint32))


@settings(max_examples=30, deadline=None)
@given(q=st.integers(0, 700), c=st.integers(1, 50), k=st.integers(1, 5), threads=st.sampled_from([1, 2, None]),
       block=st.sampled_from([1, 5, 64, 1024]), seed=st.integers(0, 2**32 - 1))
def test_topk_gemm_in_row_chunks_equals_one_block(q, c, k, threads, block, seed):
    rng = np.random.default_rng(seed)
    x = rng.integers(0, 256, (q, 16)).astype(np.float32)
    cent = rng.uniform(0, 255, (c, 16)).astype(np.float32)
    cn = np.einsum("ij,ij->i", cent, cent)
    with mock.patch.object(kernels, "_TOPK_BLOCK", block):  # thread chunks cut in GEMM blocks of `block` rows
        idx, dist = kernels.topk_gemm(x, cent, cn, k, threads)
    assert idx.shape == dist.shape == (q, k)
    # the k nearest centroids by a float64 reference; GEMMs of other shapes round differently, so distances agree
    # to float32 precision and the order may differ only between near-equal distances
    ref = ((x[:, None, :].astype(np.float64) - cent[None].astype(np.float64)) ** 2).sum(-1)
    want = np.sort(ref, 1)[:, :k]
    kk = min(k, c)
    np.testing.assert_allclose(dist[:, :kk], want[:, :kk], rtol=1e-5, atol=0.5)
    got = np.take_along_axis(ref, np.maximum(idx[:, :kk], 0), 1)
    np.testing.assert_allclose(got, want[:, :kk], rtol=1e-5, atol=0.5)
    assert np.all(idx[:, kk:] == -1) and np.all(np.isinf(dist[:, kk:]))


# --------------------------------------------------------------------------- as_exact_uint8
@settings(max_examples=50, deadline=None)
@given(n=st.integers(1, 20), d=st.integers(1, 20), fortran=st.booleans(), seed=st.integers(0, 2**32 - 1))
def test_as_exact_uint8_accepts_byte_valued_floats(n, d, fortran, seed):
    ref = np.random.default_rng(seed).integers(0, 256, (n, d), dtype=np.uint8)
    ref[0, 0], ref[-1, -1] = 0, 255
    x = ref.astype(np.float32)
    if fortran:
        x = np.asfortranarray(x)
    out = kernels.as_exact_uint8(x)
    assert out is not None and out.dtype == np.uint8 and out.shape == (n, d)
    np.testing.assert_array_equal(out, ref)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 10), d=st.integers(1, 10), bad=st.sampled_from([0.5, -1.0, 256.0, 255.5, -0.5, 1e9,
                                                                        np.nan, np.inf, -np.inf]),
       seed=st.integers(0, 2**32 - 1), where=st.sampled_from(["first", "last", "random"]))
def test_as_exact_uint8_rejects_any_non_byte_value(n, d, bad, seed, where):
    rng = np.random.default_rng(seed)
    x = rng.integers(0, 256, (n, d)).astype(np.float32)
    i, j = {"first": (0, 0), "last": (n - 1, d - 1)}.get(where, (rng.integers(n), rng.integers(d)))
    x[i, j] = bad
    assert kernels.as_exact_uint8(x) is None


@pytest.mark.parametrize("x", [
    np.zeros((3, 4), np.float64), np.zeros((3, 4), np.uint8), np.zeros((3, 4), np.int32), np.zeros((3, 4), np.float16),
    np.zeros((0, 4), np.float32), np.zeros((4, 0), np.float32), np.zeros(4, np.float32),
])
def test_as_exact_uint8_none_for_other_dtypes_and_empty(x):
    assert kernels.as_exact_uint8(x) is None


def test_as_exact_uint8_none_above_256_dimensions():
    # the uint8 distance sums in float32: exact only while 255^2 * D < 2^24
    assert kernels.as_exact_uint8(np.zeros((2, 256), np.float32)) is not None
    assert kernels.as_exact_uint8(np.zeros((2, 257), np.float32)) is None


@settings(max_examples=40, deadline=None)
@given(d=st.integers(1, 256), seed=st.integers(0, 2**32 - 1), extreme=st.booleans())
def test_uint8_distance_is_exact(d, seed, extreme):
    """The byte-valued squared L2 inside the candidate kernel equals the int64 reference bit for bit, up to the
    largest value (0 vs 255 in every one of 256 dimensions: 16,646,400)."""
    rng = np.random.default_rng(seed)
    a = np.zeros((1, d), np.uint8) if extreme else rng.integers(0, 256, (1, d), dtype=np.uint8)
    b = np.full((1, d), 255, np.uint8) if extreme else rng.integers(0, 256, (1, d), dtype=np.uint8)
    S = kernels.build_strips(np.zeros((1, 2)), 64.0)
    _, d1, _, _, n = kernels.guided_top2(np.zeros(1, np.int64), a, b, np.zeros((1, 3)), False, 1.0,
                                          np.full(1, -1.0), np.full(1, 1.0), S, S)
    ref = int(((a.astype(np.int64) - b.astype(np.int64)) ** 2).sum())
    assert n[0] == 1 and float(d1[0]) == ref


# --------------------------------------------------------------------------- DenseKnn2
def _blas_threads():
    return [(i["filepath"], i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]


@pytest.mark.parametrize("n2", [0, 1, 2, 5000])
def test_dense_knn2_equals_knn2_and_reference(n2):
    rng = np.random.default_rng(n2)
    d2 = rng.integers(0, 6, (n2, 8)).astype(np.float32)  # integer valued: GEMM distances are exact
    q = rng.integers(0, 6, (23, 8)).astype(np.float32)
    q[:3] = d2[-3:] if n2 >= 3 else q[:3]  # exact duplicates in the last chunk
    # load Numba (which may load another BLAS) before recording the thread limits
    kernels.topk_gemm_serial(np.zeros((1, 1), np.float32), np.zeros(1, np.float32), np.zeros(1, np.float32), 2)
    before = _blas_threads()
    with DenseKnn2(d2, threads=2) as dense:
        assert all(t == 1 for _, t in _blas_threads())
        if n2 == 5000:
            assert len(dense.chunks) > 1  # the cross-chunk merge is exercised
        i1, s1, i2, s2 = dense.query(q)
        empty = dense.query(q[:0])
    assert _blas_threads() == before
    for arr in empty:
        assert arr.shape == (0,)
    assert i1.dtype == np.int64 and s1.dtype == np.float64  # exact squared distances (guidedmatch.exact)
    # reference: exact integer squared distances, ties to the lower index
    ref = ((q[:, None, :].astype(np.int64) - d2[None].astype(np.int64)) ** 2).sum(-1).astype(np.float64)
    for r in range(len(q)):
        e1, e2 = ref_top2(np.arange(n2), ref[r])
        assert (i1[r], i2[r]) == (e1, e2)
        assert s1[r] == (ref[r, e1] if e1 >= 0 else np.inf)
        assert s2[r] == (ref[r, e2] if e2 >= 0 else np.inf)
    if n2 <= 1:  # missing second neighbour (and first, for n2 == 0): index -1, distance inf
        np.testing.assert_array_equal(i2, -1)
        assert np.all(np.isinf(s2))
    if n2 == 0:
        np.testing.assert_array_equal(i1, -1)
        assert np.all(np.isinf(s1))
    (k1, kd1, k2, kd2), _ = knn2(q, d2)
    np.testing.assert_array_equal(i1, k1)
    np.testing.assert_array_equal(i2, k2)
    np.testing.assert_array_equal(l2(s1), kd1)  # the same exact distances, bit for bit
    np.testing.assert_array_equal(l2(s2), kd2)


def test_dense_knn2_restores_blas_limits_after_an_exception():
    d2 = np.zeros((3000, 4), np.float32)
    kernels.topk_gemm_serial(np.zeros((1, 1), np.float32), np.zeros(1, np.float32), np.zeros(1, np.float32), 2)
    before = _blas_threads()
    with pytest.raises(RuntimeError):
        with DenseKnn2(d2, threads=2):
            raise RuntimeError("boom")
    assert _blas_threads() == before


def test_band_edge_point_exact_for_integer_descriptors():
    # |a*x + b*y + c| is exactly 1.0 in plain float64 but 1.0000000000000182 when contracted into FMAs
    a, b, c = -0.41712332493858084, 0.9088498950828916, 376.47774069425947
    x, y = 97.04889326126471, -368.59374190163487
    assert abs(a * x + b * y + c) == 1.0
    P = np.array([[x, y]])
    d = np.zeros((1, 1), np.uint8)
    r = kernels.guided_top2(np.zeros(1, np.int64), d, d, np.array([[a, b, c]]), True, 1.0,
                            np.array([-np.inf]), np.array([np.inf]),
                            kernels.build_strips(P, 24.0, 0), kernels.build_strips(P, 24.0, 1))
    assert r[4][0] == 1 and r[0][0] == 0


# --------------------------------------------------------------------------- work bound
def _occupied_strips_crossed(S, pts2, line, band, lo, hi):
    """Reference bound: the occupied strips of ``S`` that hold a point whose x lies in [lo, hi] and whose other
    coordinate lies within the band's extent over the strip -- i.e. strips the band really crosses inside the
    points' bounding box -- plus one strip either side for the cell-edge slack."""
    sid = np.minimum(((pts2[:, 0] - S.u0) // S.width).astype(np.int64), S.nstrips - 1)  # column strips (axis 0)
    occupied = np.unique(sid)
    a, b, c = line
    # a strip counts when the band's y-range over the strip's x-interval meets the points' y-extent
    ky0, ky1 = S.k0, S.k0 + S.ncells * S.cell
    xs0 = S.u0 + occupied * S.width
    ya, yb = -(a * xs0 + c) / b, -(a * (xs0 + S.width) + c) / b
    m = band / abs(b)
    meets = (np.maximum(ya, yb) + m >= ky0) & (np.minimum(ya, yb) - m <= ky1) & (xs0 + S.width >= lo) & (xs0 <= hi)
    return int(meets.sum()) + 2


@pytest.mark.parametrize("kind", ["u8", "f32"])
def test_guided_top2_extreme_homography_work_bounded(kind):
    """Aligned image-2 points spread over ~1e6 px by a near-degenerate homography (the printed approach (c) on a
    wide pair): results equal the reference and each query visits only occupied strips its band crosses, not
    the ~N strips the spread's coordinate range makes."""
    rng = np.random.default_rng(11)
    n2, nq = 1500, 200
    img = rng.uniform(0, [3072, 2048], (n2, 2))
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1 / 3100.0, 0.0, 1.0]])  # x -> 3100 sent to infinity
    q = np.c_[img, np.ones(n2)] @ H.T
    pts2 = q[:, :2] / q[:, 2:]
    assert np.ptp(pts2[:, 0]) > 1e5  # the frame spreads over a coordinate range far beyond the image
    desc1 = make_desc(kind, rng, nq, 16, small=False)
    desc2 = make_desc(kind, rng, n2, 16, small=False)
    # near-horizontal lines through random points, slopes up to 0.2; half with an x-range, half unbounded
    p = pts2[rng.integers(0, n2, nq)]
    slope = rng.uniform(-0.2, 0.2, nq)
    lines = np.c_[-slope, np.ones(nq), slope * p[:, 0] - p[:, 1]]
    lines /= np.hypot(lines[:, 0], lines[:, 1])[:, None]
    xlo = np.where(np.arange(nq) % 2 == 0, -np.inf, p[:, 0] - 5e4)
    xhi = np.where(np.arange(nq) % 2 == 0, np.inf, p[:, 0] + 5e4)
    band = 5.0
    cols = kernels.build_strips(pts2, 40.0, axis=0)
    rows = kernels.build_strips(pts2, 40.0, axis=1)
    queries = np.arange(nq)
    run_and_check(queries, desc1, desc2, kind, pts2, lines, True, band, xlo, xhi, cols, rows)
    res = kernels.guided_top2(queries, kernel_desc(kind, desc1), kernel_desc(kind, desc2), lines, True, band,
                              xlo, xhi, cols, rows, return_visits=True)
    nvisit = res[5]
    assert cols.nstrips > 1000  # the strip table itself is large (N-sized) ...
    bound = [_occupied_strips_crossed(cols, pts2, lines[k], band, xlo[k], xhi[k]) for k in range(nq)]
    assert np.all(nvisit <= bound)  # ... but each query walks only the occupied strips its band crosses
    assert nvisit.sum() < 0.1 * nq * cols.nstrips


def test_first_nonempty():
    pts = np.array([[0.0, 0.0], [0.5, 1.0], [10.0, 0.0], [30.0, 0.0]])
    S = kernels.build_strips(pts, 5.0, axis=0, cell=5.0)
    first = kernels.first_nonempty(S)
    occupied = {int((x - S.u0) // S.width) for x in pts[:, 0]}
    for s in range(S.nstrips + 1):
        want = min([o for o in occupied if o >= s], default=S.nstrips)
        assert first[s] == want


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(0, 40), st.just(2)),
              elements=st.floats(-200, 200, allow_nan=False, allow_infinity=False)),
       st.floats(0.5, 30.0), st.integers(0, 1))
def test_first_nonempty_equals_a_loop(pts, width, axis):
    S = kernels.build_strips(pts, width, axis=axis)
    ns, nk, off = S.nstrips, S.ncells, S.offsets
    want = np.empty(ns + 1, np.int64)
    want[ns] = ns
    for s in range(ns - 1, -1, -1):  # the loop the Numba kernel ran before
        want[s] = s if off[(s + 1) * nk] > off[s * nk] else want[s + 1]
    got = kernels.first_nonempty(S)
    assert got.dtype == np.int64 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)


def test_chunked_runs_in_threads_and_survives_a_fork():
    import multiprocessing
    import threading

    seen = set()

    def fn(a, b):
        seen.add(threading.get_ident())
        return (a, b)

    parts = kernel_threads._chunked(fn, 1000, 100, threads=2)
    assert parts == [(0, 500), (500, 1000)] and len(seen) == 2  # contiguous chunks, in order, two threads
    assert kernel_threads._chunked(fn, 99, 100, threads=2) == [(0, 99)]  # small: the calling thread only
    if "fork" not in multiprocessing.get_all_start_methods():
        pytest.skip("no fork on this platform")
    ctx = multiprocessing.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=lambda: q.put(kernel_threads._chunked(lambda a, b: b - a, 1000, 100, threads=2)))
    p.start()
    p.join(60)
    if p.exitcode is None:
        p.kill()
        p.join()
    assert p.exitcode == 0, "a forked child must not hang on its parent's thread pool"
    assert q.get(timeout=5) == [500, 500]


def test_limit_threads_here_caps_only_the_calling_thread():
    import threading

    from guidedmatch import kernels

    before = kernels.num_threads()
    seen = []

    def worker():
        kernels.limit_threads_here(1)
        seen.append(kernels.num_threads())

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert seen == [1] and kernels.num_threads() == before
