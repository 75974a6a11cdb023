"""Retrieval pairs from the collection's own visual words (guidedmatch.collection.retrieval)."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import scipy.sparse as sp

from guidedmatch.cli import main as cli_main
from guidedmatch.collection.pairs import exhaustive_pairs, pairs_from_spec, sequential_pairs
from guidedmatch.collection.retrieval import (RetrievalConfig, bag_of_words, parse_retrieval_spec, retrieval_pairs,
                                              shortlist)
from guidedmatch.errors import ConfigError

SMALL = dict(coarse=32, fine=32, sample=20_000, progress=False)  # 1024 words: enough for ~800 features per view


@pytest.fixture(scope="module")
def two_scenes(tmp_path_factory):
    """A COLMAP database of two rendered multi-view scenes (5 overlapping views + 1 view looking away, each)."""
    from guidedmatch.collection.sources import images_to_database
    from guidedmatch.testing.multiview import make_multiview, write_views

    d = tmp_path_factory.mktemp("retrieval")
    scenes = {}
    for s in range(2):
        mv = make_multiview(5, (640, 480), seed=10 + s, isolated=True, spacing=1.2)
        paths = write_views(mv, d / "img" / f"s{s}")
        for i, p in enumerate(paths):
            scenes[f"s{s}/{p.name}"] = (s, i in mv.isolated, mv.overlap[i])
    src = images_to_database(d / "img", d / "db.db", progress=False)
    src.close()
    return d / "db.db", scenes


def _source(db):
    from guidedmatch.collection.sources import ColmapSource

    return ColmapSource(db)


def test_shortlist_pairs_overlapping_views_and_never_two_unrelated_connected_views(two_scenes, tmp_path):
    db, scenes = two_scenes
    src = _source(db)
    res = retrieval_pairs(src, None, dict(SMALL, k=2), cache=tmp_path / "r.npz")
    connected = [n for n, (_, iso, _) in scenes.items() if not iso]
    partners = {n: set() for n in scenes}
    for a, b in res.pairs:
        partners[a].add(b)
        partners[b].add(a)
        if a in connected and b in connected:
            assert scenes[a][0] == scenes[b][0], f"unrelated views paired: {a} {b}"
    names = src.names()
    for n in connected:
        s, _, overlap = scenes[n]
        same = [m for m in partners[n] if scenes[m][0] == s and overlap[names.index(m) % 6] > 0]
        assert len(same) >= 2, (n, partners[n])
    assert res.info["words"] == 1024 and res.info["reused"] == "none"


def test_stage_is_resumed_from_its_file_and_a_new_k_reuses_the_vocabulary(two_scenes, tmp_path):
    db, _ = two_scenes
    src = _source(db)
    cache = tmp_path / "r.npz"
    first = retrieval_pairs(src, None, dict(SMALL, k=2), cache=cache)
    again = retrieval_pairs(src, None, dict(SMALL, k=2), cache=cache)
    assert again.info["reused"] == "all" and again.pairs == first.pairs
    k3 = retrieval_pairs(src, None, dict(SMALL, k=3), cache=cache)
    fresh = retrieval_pairs(src, None, dict(SMALL, k=3), cache=None)
    assert k3.info["reused"] == "vocabulary" and k3.pairs == fresh.pairs
    other_seed = retrieval_pairs(src, None, dict(SMALL, k=3, seed=1), cache=cache)
    assert other_seed.info["reused"] == "none"
    cache.write_bytes(b"not an npz: a torn or foreign file is rebuilt")
    rebuilt = retrieval_pairs(src, None, dict(SMALL, k=3), cache=cache)
    assert rebuilt.info["reused"] == "none" and rebuilt.pairs == fresh.pairs


def test_k_of_at_least_n_minus_1_is_exactly_exhaustive(two_scenes, tmp_path):
    db, _ = two_scenes
    src = _source(db)
    names = src.names()
    for k in (len(names) - 1, len(names) + 5):
        pl = pairs_from_spec(f"retrieval:{k}", names, src, retrieval=SMALL, retrieval_cache=None)
        assert pl.pairs == exhaustive_pairs(names).pairs


def test_specs_combine_with_plus_as_the_union(two_scenes):
    db, _ = two_scenes
    src = _source(db)
    names = src.names()
    seq = sequential_pairs(names, 2)
    ret = pairs_from_spec("retrieval:2", names, src, retrieval=SMALL, retrieval_cache=None)
    both = pairs_from_spec("sequential:2+retrieval:2", names, src, retrieval=SMALL, retrieval_cache=None)
    assert {frozenset(p) for p in both} == {frozenset(p) for p in seq} | {frozenset(p) for p in ret}
    assert len(both) == len({frozenset(p) for p in both})
    assert both.report["retrieval"]["k"] == 2 and set(both.report["parts"]) == {"sequential:2", "retrieval:2"}


@pytest.mark.parametrize("spec", ["retrieval:0", "retrieval:x", "retrieval:-1", "retrieval:", "retrieval:2:3",
                                  "retrieval:2.5", "sequential:2+", "+retrieval"])
def test_bad_specs_are_config_errors(spec):
    with pytest.raises(ConfigError):
        pairs_from_spec(spec, ["a", "b", "c"], source=object())


def test_retrieval_without_a_source_is_a_config_error():
    with pytest.raises(ConfigError, match="needs the feature source"):
        pairs_from_spec("retrieval:3", ["a", "b", "c"])
    assert parse_retrieval_spec("retrieval") == RetrievalConfig().k


@pytest.mark.parametrize("spec", ["retrieval:0", "retrieval:x"])
def test_cli_bad_spec_is_exit_2_before_any_work(two_scenes, tmp_path, capsys, spec):
    db, _ = two_scenes
    copy = tmp_path / "db.db"
    shutil.copyfile(db, copy)
    rc = cli_main(["colmap", str(copy), "--pairs", spec, "--no-progress", "--log", "none"])
    err = capsys.readouterr().err
    assert rc == 2 and "retrieval[:K]" in err and "Traceback" not in err
    assert not (tmp_path / "db.db.retrieval.npz").exists()


def _bow_reference(counts, n_words):
    """Slow reference: dense loops over images and words."""
    n = len(counts)
    tf = np.zeros((n, n_words))
    for i, (w, c) in enumerate(counts):
        for ww, cc in zip(w, c):
            tf[i, ww] += cc
    df = (tf > 0).sum(0)
    idf = np.log(n / np.maximum(df, 1))
    out = np.zeros_like(tf)
    for i in range(n):
        total = tf[i].sum()
        v = np.sqrt(tf[i] / max(total, 1)) * idf
        norm = np.linalg.norm(v)
        out[i] = v / norm if norm > 0 else v
    return out


def test_bag_of_words_and_shortlist_match_slow_references():
    rng = np.random.default_rng(3)
    n, words = 30, 50
    counts = []
    for _ in range(n):
        w = np.unique(rng.integers(0, words, rng.integers(1, 30)))
        counts.append((w, rng.integers(1, 5, len(w))))
    bow = bag_of_words(counts, words)
    ref = _bow_reference(counts, words)
    np.testing.assert_allclose(bow.toarray(), ref, atol=1e-6)
    sim = ref @ ref.T
    np.fill_diagonal(sim, -np.inf)
    assert len(np.unique(np.round(sim[np.isfinite(sim)], 5))) > 0.4 * n * (n - 1)  # few exact ties: ranking defined
    for k in (1, 3, 7):
        want = set()
        for i in range(n):
            for j in np.argsort(-sim[i], kind="stable")[:k]:
                want.add((min(i, j), max(i, j)))
        got = {tuple(p) for p in shortlist(sp.csr_matrix(ref.astype(np.float32)), k, block=7)}
        assert got == want, (k, got ^ want)
    # hub-corrected ranking (CSLS): 2 cos - r_i - r_j, r = mean of the 4 largest cosines of each image
    r = np.array([np.sort(sim[i][np.isfinite(sim[i])])[-4:].mean() for i in range(n)])
    csls = 2 * sim - r[:, None] - r[None, :]
    want = {(min(i, j), max(i, j)) for i in range(n) for j in np.argsort(-csls[i], kind="stable")[:3]}
    got = {tuple(p) for p in shortlist(sp.csr_matrix(ref.astype(np.float32)), 3, block=7, hub_k=4)}
    assert got == want
