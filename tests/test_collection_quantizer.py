"""Tests of guidedmatch.collection.quantizer (one IVF coarse quantizer for a collection) and of the prepared images'
shared-quantizer path (guidedmatch.prepared: query_cells, search2 with cells)."""
import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from guidedmatch.collection import quantizer as Q
from guidedmatch.collection.config import CollectionConfig, collection_matcher_config
from guidedmatch.collection.engine import match_collection
from guidedmatch.errors import ConfigError, InputError
from guidedmatch.features import Features
from guidedmatch.matcher import match
from guidedmatch.prepared import PreparedConfig, prepare
from guidedmatch.testing.arc_views import arc_views


def _descriptors(n, seed, dim=32, byte=True):
    rng = np.random.default_rng(seed)
    centres = rng.integers(0, 200, (20, dim))
    d = np.clip(centres[rng.integers(0, 20, n)] + rng.integers(-30, 30, (n, dim)), 0, 255).astype(np.float32)
    return d if byte else d + rng.uniform(0, 1, d.shape).astype(np.float32)


def _features(n, seed, dim=32, byte=True):
    rng = np.random.default_rng(seed + 1000)
    return Features(rng.uniform(0, 639, (n, 2)), _descriptors(n, seed, dim, byte), (640, 480), "sift")


def _ref_cells(q, cent, nprobe):
    """Slow reference: each row's nprobe nearest centroids (float64 distances, ties by the lower index), in cell
    order."""
    d = ((q[:, None, :].astype(np.float64) - cent[None].astype(np.float64)) ** 2).sum(-1)
    out = np.empty((len(q), nprobe), np.int64)
    for r in range(len(q)):
        out[r] = np.sort(sorted(range(len(cent)), key=lambda c: (d[r, c], c))[:nprobe])
    return out


def test_train_quantizer_is_seeded_and_validated():
    x = _descriptors(3000, 0)
    a, b = Q.train_quantizer(x, 50), Q.train_quantizer(x, 50)
    assert a.nlist == 50 and a.dim == 32 and a.token == b.token and np.array_equal(a.centroids, b.centroids)
    assert Q.train_quantizer(x, 50, seed=1).token != a.token
    with pytest.raises(InputError):
        Q.train_quantizer(x[:10], 50)
    with pytest.raises(InputError):
        Q.SharedQuantizer(np.full((3, 4), np.nan))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31 - 1), st.booleans(), st.sampled_from([1, 4, 7]))
def test_query_cells_are_the_exact_nearest_cells(seed, byte, nprobe):
    f = _features(1500, seed % 1000, byte=byte)
    q = Q.train_quantizer(_descriptors(2000, seed % 1000 + 1, byte=byte), 40, seed=seed % 7)
    p = prepare(f, PreparedConfig(nprobe=nprobe), quantizer=q)
    cells, sq = p.query_cells(nprobe)
    assert cells.shape == (len(f), nprobe) and cells.dtype == np.int64
    np.testing.assert_array_equal(cells, _ref_cells(f.descriptors, q.centroids, nprobe))
    assert p.query_cells(nprobe)[0] is cells  # computed once


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1), st.booleans())
def test_search_with_looked_up_cells_equals_the_search_computing_them(seed, byte):
    f1, f2 = _features(1300, seed % 997, byte=byte), _features(1700, seed % 997 + 3, byte=byte)
    q = Q.train_quantizer(np.concatenate([f1.descriptors, f2.descriptors]), 60)
    p1, p2 = prepare(f1, quantizer=q), prepare(f2, quantizer=q)
    rows = np.random.default_rng(seed).permutation(len(f1))[:400]
    cells = tuple(a[rows] for a in p1.query_cells(p2.nprobe))
    got = p2.search2(f1.descriptors[rows], byte_exact=p1.byte_exact, cells=cells)
    want = p2.search2(f1.descriptors[rows], byte_exact=p1.byte_exact)
    for g, w in zip(got, want):
        assert np.array_equal(g, w)


def test_a_shared_index_uses_the_collection_cells_and_no_kmeans():
    f = _features(2000, 1)
    q = Q.train_quantizer(_descriptors(3000, 2), 30)
    p = prepare(f, quantizer=q)
    assert p.nlist == 30 and p.build_comparisons == 2000 * 30  # every descriptor assigned once, nothing trained
    index = p.index()
    cent = index.quantizer.reconstruct_n(0, index.nlist)
    assert np.array_equal(cent, q.centroids) and index.ntotal == 2000
    own = prepare(f)
    assert own.nlist == round(2 * np.sqrt(2000)) and own.build_comparisons > 2000 * own.nlist


def test_matches_with_the_image_cells_equal_those_computed_per_pair():
    """Image 1 with the shared quantizer (cells looked up) vs without it (the coarse step per pair against image 2's
    same shared centroids): the same matches, bit for bit."""
    views = arc_views(2, 2600, 0, shuffle=False)
    a, b = views["view0.jpg"], views["view1.jpg"]
    q = Q.train_quantizer(np.concatenate([a.descriptors, b.descriptors]), 70)
    cfg = collection_matcher_config()
    p2 = prepare(b, quantizer=q)
    looked_up = match(prepare(a, quantizer=q), p2, "so+epi+ia", cfg)
    computed = match(prepare(a), p2, "so+epi+ia", cfg)
    assert looked_up.geometry.verdict == "verified" and len(looked_up) > 100
    assert looked_up.pairs.tobytes() == computed.pairs.tobytes()
    assert looked_up.distances.tobytes() == computed.distances.tobytes()
    assert looked_up.stats.comparisons == computed.stats.comparisons


def test_pickling_keeps_the_quantizer_and_drops_the_cells():
    q = Q.train_quantizer(_descriptors(2000, 3), 30)
    p = prepare(_features(1200, 4), quantizer=q)
    p.query_cells(4)
    p.index()
    r = pickle.loads(pickle.dumps(p))
    assert r.quantizer.token == q.token and r._cells == {} and r._index is None
    np.testing.assert_array_equal(r.query_cells(4)[0], p.query_cells(4)[0])


def test_probes_cover_an_image_as_its_own_index_would_and_small_images_keep_their_own():
    q = Q.train_quantizer(_descriptors(8000, 5), 120)          # sized for ~3600 features per image
    same = prepare(_features(3600, 6), quantizer=q)
    smaller = prepare(_features(2500, 7), quantizer=q)          # own nlist 100 >= 0.8 * 120: shared, more probes
    tiny = prepare(_features(1500, 8), quantizer=q)             # own nlist 77 < 96: its own k-means
    assert same.quantizer is q and same.nprobe == 4
    assert smaller.quantizer is q and smaller.nprobe == round(4 * 120 / 100)
    assert tiny.quantizer is None and tiny.nlist == 77 and tiny.nprobe == 4


def test_a_quantizer_of_another_dimension_is_refused():
    q = Q.train_quantizer(_descriptors(2000, 3, dim=16), 30)
    with pytest.raises(InputError, match="16-D"):
        prepare(_features(1200, 4, dim=32), quantizer=q)


class _Source:
    def __init__(self, feats):
        self.feats = feats

    def names(self):
        return list(self.feats)

    def num_features(self, n):
        return len(self.feats[n])

    def load(self, n):
        return self.feats[n]

    def close(self):
        pass


def test_collection_quantizer_rules():
    m = collection_matcher_config()
    big = _Source({f"im{i:02d}": _features(1100, i) for i in range(Q.MIN_IMAGES)})
    q, info = Q.collection_quantizer(big, m, "auto")
    assert info["used"] and q.nlist == round(2 * np.sqrt(1100)) and info["images"] == Q.MIN_IMAGES
    again, info2 = Q.collection_quantizer(big, m, "auto")
    assert again is q and info2["reused"]
    small = _Source({f"im{i}": _features(1100, i) for i in range(3)})
    assert Q.collection_quantizer(small, m, "auto") == (None, dict(used=False, why="3 images, fewer than 16 "
                                                                                 "(shared_quantizer='auto')"))
    assert Q.collection_quantizer(small, m, "on")[1]["used"]
    assert Q.collection_quantizer(big, m, "off")[0] is None
    assert Q.collection_quantizer(big, collection_matcher_config(dict(unguided_index=False)), "on")[0] is None
    few = _Source({f"im{i}": _features(500, i) for i in range(3)})
    assert "min_features" in Q.collection_quantizer(few, m, "on")[1]["why"]
    rng = np.random.default_rng(0)
    orb = _Source({f"im{i}": Features(rng.uniform(0, 99, (1100, 2)), rng.integers(0, 256, (1100, 32), np.uint8),
                                      (100, 100), "orb") for i in range(3)})
    assert "binary" in Q.collection_quantizer(orb, m, "on")[1]["why"]
    with pytest.raises(ConfigError):
        CollectionConfig(shared_quantizer="yes")


def test_a_collection_run_reports_its_quantizer_and_matches_as_prepared_by_hand():
    views = arc_views(3, 2600, 0, shuffle=False, unrelated=2200)
    names = sorted(views)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    rows = {}

    class Sink:
        def done_pairs(self):
            return set()

        def write(self, a, b, p, s, g):
            rows[frozenset((a, b))] = (p.tobytes(), s.tobytes(), g.verdict)

    rep = match_collection(_Source(views), pairs, Sink(), dict(progress=False, workers=0, threads=2,
                                                                shared_quantizer="on"))
    info = rep.totals["quantizer"]
    assert info["used"] and rep.done == len(pairs)
    q, _ = Q.collection_quantizer(_Source(views), collection_matcher_config(), "on")
    assert q.token == info["token"]
    prepared = {n: prepare(views[n], quantizer=q) for n in names}
    for a, b in pairs:
        r = match(prepared[a], prepared[b], "so+epi+ia", collection_matcher_config())
        assert rows[frozenset((a, b))] == (r.pairs.tobytes(), r.distances.tobytes(), r.geometry.verdict)
    off = match_collection(_Source(views), pairs, Sink(), dict(progress=False, workers=0))  # the default
    assert off.totals["quantizer"] == dict(used=False, why="shared_quantizer='off'")
    auto = match_collection(_Source(views), pairs, Sink(), dict(progress=False, workers=0, shared_quantizer="auto"))
    assert not auto.totals["quantizer"]["used"] and "fewer than 16" in auto.totals["quantizer"]["why"]


def test_cli_shared_quantizer_reaches_the_run_and_its_log(sequence_db, tmp_path, capsys):
    """The rendered sequence has ~500 features per image: "on" passes the 16-image rule and stops at min_features
    (reported), the default "off" says so."""
    import json
    import shutil

    from guidedmatch.cli import main as cli_main

    db, log = tmp_path / "db.db", tmp_path / "log.jsonl"
    shutil.copyfile(sequence_db, db)
    assert cli_main(["colmap", str(db), "--shared-quantizer", "on", "--no-second-look", "--inlier-px", "0",
                     "--no-progress", "--log", str(log)]) == 0
    summary = [json.loads(line) for line in log.read_text().splitlines() if '"summary"' in line][-1]
    assert not summary["quantizer"]["used"] and "min_features = 1024" in summary["quantizer"]["why"]
    db.unlink()
    shutil.copyfile(sequence_db, db)
    assert cli_main(["colmap", str(db), "--no-second-look", "--no-progress", "--log", str(log)]) == 0
    summary = [json.loads(line) for line in log.read_text().splitlines() if '"summary"' in line][-1]
    assert summary["quantizer"] == dict(used=False, why="shared_quantizer='off'")
    with pytest.raises(SystemExit) as exc:
        cli_main(["colmap", str(db), "--shared-quantizer", "maybe"])
    assert exc.value.code == 2 and "invalid choice: 'maybe'" in capsys.readouterr().err
