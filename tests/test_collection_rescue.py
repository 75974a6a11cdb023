"""Rescue of rejected pairs: the third-view confirmation against a slow reference, and a rejected true pair of a
rendered multi-view scene brought back."""
import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from guidedmatch.collection.rescue import RescueConfig, confirmed_by_third_view, rescue_pairs
from guidedmatch.errors import ConfigError


def _slow_third_view(a, b, inliers, verified, contradicted: bool = False):
    """Every inlier, every third image, dictionaries: obviously correct. Per inlier ``(i, j)`` of ``a``-``b``: some
    third image ``c`` with verified ``a``-``c`` and ``b``-``c`` maps ``i`` and ``j`` to the same keypoint of ``c``
    (confirmed) -- or, with ``contradicted``, to different ones."""
    def partner(x, c):
        key = (min(x, c), max(x, c))
        if key not in verified:
            return None
        col = 0 if x < c else 1
        return {int(r[col]): int(r[1 - col]) for r in verified[key]}

    out = []
    images = {k for p in verified for k in p} - {a, b}
    for i, j in inliers:
        hit = False
        for c in images:
            pa, pb = partner(a, c), partner(b, c)
            if pa is not None and pb is not None and i in pa and j in pb and (pa[i] != pb[j]) == contradicted:
                hit = True
        out.append(hit)
    return out


def _one_to_one(rng, n1, n2, k):
    k = min(k, n1, n2)
    return np.stack([rng.choice(n1, k, replace=False), rng.choice(n2, k, replace=False)], axis=1)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(3, 6))
def test_confirmed_by_third_view_matches_the_slow_reference(seed, n_images):
    rng = np.random.default_rng(seed)
    nkp = {i: int(rng.integers(5, 30)) for i in range(1, n_images + 1)}
    verified = {}
    for a in nkp:
        for b in nkp:
            if a < b and (a, b) != (1, 2) and rng.random() < 0.7:
                verified[(a, b)] = _one_to_one(rng, nkp[a], nkp[b], int(rng.integers(1, 20)))
    inliers = _one_to_one(rng, nkp[1], nkp[2], 12)
    got = confirmed_by_third_view(1, 2, inliers, verified, nkp)
    assert got.tolist() == _slow_third_view(1, 2, inliers, verified)


def test_rescue_config_is_validated():
    with pytest.raises(ConfigError):
        RescueConfig(matcher="magic")
    with pytest.raises(Exception):
        RescueConfig(min_share=1.5)


@pytest.fixture(scope="module")
def matched_db(tmp_path_factory):
    """Four rendered views of one scene, features in a COLMAP database, every pair matched by ``guidedmatch colmap``."""
    from guidedmatch.cli import main
    from guidedmatch.collection.sources import images_to_database
    from guidedmatch.testing.multiview import make_multiview, write_views

    mv = make_multiview(5, (640, 480), seed=3, isolated=False)
    root = tmp_path_factory.mktemp("rescue")
    write_views(mv, root / "img")
    images_to_database(root / "img", root / "db.db", max_features=2000, progress=False).close()
    assert main(["colmap", str(root / "db.db"), "--no-progress", "--log", "none"]) == 0
    return root / "db.db"


def _geometries(path):
    db = pycolmap.Database.open(str(path))
    try:
        ids = sorted(img.image_id for img in db.read_all_images())
        return {(a, b): len(db.read_two_view_geometry(a, b).inlier_matches)
                for k, a in enumerate(ids) for b in ids[k + 1:] if db.exists_two_view_geometry(a, b)}
    finally:
        db.close()


def test_a_rejected_true_pair_is_brought_back(matched_db, tmp_path):
    import shutil

    path = tmp_path / "db.db"
    shutil.copy(matched_db, path)
    before = _geometries(path)
    verified = [p for p, n in before.items() if n >= 30]
    nb = {k: {q for p in verified for q in p if k in p} - {k} for p in verified for k in p}
    a, b = next(p for p in verified if nb[p[0]] & nb[p[1]])   # a verified pair that closes a triangle
    db = pycolmap.Database.open(str(path))   # what our verdict writes for a no-overlap pair: no matches, no inliers
    g = db.read_two_view_geometry(a, b)
    g.inlier_matches = np.zeros((0, 2), np.uint32)
    g.config = 1
    db.update_two_view_geometry(a, b, g)
    db.delete_matches(a, b)
    db.write_matches(a, b, np.zeros((0, 2), np.uint32))
    db.close()
    rep = rescue_pairs(path, RescueConfig(matcher="colmap", num_threads=1))
    assert rep["candidates"] == 1 and rep["colmap_verified"] == 1 and rep["kept"] == 1
    after = _geometries(path)
    assert after[(a, b)] >= 15 and rep["per_pair"][0]["confirmed"] >= 8
    assert {p: n for p, n in after.items() if p != (a, b)} == {p: n for p, n in before.items() if p != (a, b)}
    again = rescue_pairs(path, RescueConfig(matcher="colmap", num_threads=1))   # nothing left to rescue
    assert again["candidates"] == 0


def test_a_pair_no_third_view_confirms_is_refused(matched_db, tmp_path):
    import shutil

    path = tmp_path / "db.db"
    shutil.copy(matched_db, path)
    before = _geometries(path)
    a, b = [p for p, n in before.items() if n >= 30][0]
    db = pycolmap.Database.open(str(path))
    for p in before:   # leave only a-b rejected and no other verified pair touching a: no triangle, no candidate
        if a in p and p != (a, b):
            g = db.read_two_view_geometry(*p)
            g.inlier_matches = np.zeros((0, 2), np.uint32)
            g.config = 1
            db.update_two_view_geometry(*p, g)
    g = db.read_two_view_geometry(a, b)
    g.inlier_matches = np.zeros((0, 2), np.uint32)
    g.config = 1
    db.update_two_view_geometry(a, b, g)
    db.close()
    rep = rescue_pairs(path, RescueConfig(matcher="colmap", num_threads=1))
    assert rep["candidates"] == 0 and rep["kept"] == 0
    assert _geometries(path)[(a, b)] == 0


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(3, 6))
def test_contradicted_by_third_view_matches_the_slow_reference(seed, n_images):
    from guidedmatch.collection.rescue import contradicted_by_third_view

    rng = np.random.default_rng(seed)
    nkp = {i: int(rng.integers(5, 30)) for i in range(1, n_images + 1)}
    verified = {(a, b): _one_to_one(rng, nkp[a], nkp[b], int(rng.integers(1, 20)))
                for a in nkp for b in nkp if a < b and (a, b) != (1, 2) and rng.random() < 0.7}
    inliers = _one_to_one(rng, nkp[1], nkp[2], 12)
    got = contradicted_by_third_view(1, 2, inliers, verified, nkp)
    assert got.tolist() == _slow_third_view(1, 2, inliers, verified, contradicted=True)
