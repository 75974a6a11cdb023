"""Pair lists: exhaustive, COLMAP's sequential semantics, pairs files, normalization and its report."""
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from guidedmatch.collection.pairs import (exhaustive_pairs, normalize_pairs, pairs_from_spec, read_pairs_file,
                                          sequential_pairs, write_pairs_file)
from guidedmatch.errors import ConfigError, InputError

NAMES = [f"img{i:03d}.jpg" for i in range(40)]


def _colmap_sequential_reference(names, overlap, quadratic):
    """COLMAP's SequentialPairGenerator, restated: sorted names; offsets 1..K or 2^0..2^(K-1)."""
    seq = sorted(names)
    offsets = [2**k for k in range(overlap)] if quadratic else list(range(1, overlap + 1))
    return {(seq[i], seq[i + d]) for i in range(len(seq)) for d in offsets if i + d < len(seq)}


@settings(max_examples=60, deadline=None)
@given(n=st.integers(0, 40), overlap=st.integers(1, 12), quadratic=st.booleans(), seed=st.randoms())
def test_sequential_matches_colmap_semantics(n, overlap, quadratic, seed):
    names = NAMES[:n]
    seed.shuffle(names)  # COLMAP orders by name whatever the input order
    pl = sequential_pairs(names, overlap, quadratic)
    assert set(pl.pairs) == _colmap_sequential_reference(names, overlap, quadratic)
    assert len(pl.pairs) == len(set(pl.pairs))


def test_sequential_given_order_and_validation():
    assert sequential_pairs(["b", "a", "c"], 1, order="given").pairs == (("b", "a"), ("a", "c"))
    with pytest.raises(ConfigError):
        sequential_pairs(["a", "b"], 0)
    with pytest.raises(ConfigError):
        sequential_pairs(["a", "b"], 2, order="random")
    with pytest.raises(InputError, match="unique"):
        sequential_pairs(["a", "a"], 2)


@given(n=st.integers(0, 25))
def test_exhaustive(n):
    pl = exhaustive_pairs(NAMES[:n])
    assert len(pl) == n * (n - 1) // 2
    assert {frozenset(p) for p in pl} == {frozenset((a, b)) for a in NAMES[:n] for b in NAMES[:n] if a != b}


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6)), max_size=40))
def test_normalize_counts_and_order(raw):
    names = [f"n{i}" for i in range(7)]
    pairs = [(names[a], names[b]) for a, b in raw]
    pl = normalize_pairs(pairs, names)
    r = pl.report
    assert r["input"] == len(pairs)
    assert r["input"] == (len(pl) + r["self_pairs"]["count"] + r["duplicates"]["count"]
                          + r["reversed_duplicates"]["count"])
    assert all(a != b for a, b in pl.pairs)
    assert len({frozenset(p) for p in pl.pairs}) == len(pl.pairs)
    assert {frozenset(p) for p in pl.pairs} == {frozenset(p) for p in pairs if p[0] != p[1]}
    # first occurrence of each unordered pair kept, in input order, with its given orientation
    first = {}
    for p in pairs:
        if p[0] != p[1]:
            first.setdefault(frozenset(p), p)
    assert list(pl.pairs) == list(first.values())
    assert r["self_pairs"]["count"] == sum(a == b for a, b in pairs)


def test_pairs_file(tmp_path):
    f = tmp_path / "pairs.txt"
    f.write_bytes(b"# comment\r\nimg000.jpg img001.jpg\r\n\r\n  img001.jpg   img000.jpg\nimg002.jpg img002.jpg\n"
                  b"img000.jpg img001.jpg\nimg003.jpg\timg004.jpg\n")
    pl = read_pairs_file(f, NAMES)
    assert pl.pairs == (("img000.jpg", "img001.jpg"), ("img003.jpg", "img004.jpg"))
    r = pl.report
    assert (r["reversed_duplicates"]["count"], r["self_pairs"]["count"], r["duplicates"]["count"]) == (1, 1, 1)
    assert r["reversed_duplicates"]["examples"][0] == {"pair": ["img001.jpg", "img000.jpg"], "at": "line 4"}
    assert "1 reversed duplicates dropped" in pl.summary()
    out = tmp_path / "out.txt"
    write_pairs_file(out, pl.pairs)
    assert read_pairs_file(out, NAMES).pairs == pl.pairs


def test_pairs_file_errors(tmp_path):
    f = tmp_path / "pairs.txt"
    f.write_text("img000.jpg img001.jpg\nimg000.jpg nope.jpg\nghost.png img001.jpg\n")
    with pytest.raises(InputError) as e:
        read_pairs_file(f, NAMES)
    msg = str(e.value)
    assert "'nope.jpg' (line 2)" in msg and "'ghost.png' (line 3)" in msg and "2 image name(s)" in msg
    f.write_text("img000.jpg img001.jpg extra\n")
    with pytest.raises(InputError, match=r"pairs.txt:1: expected .name1 name2., got 3"):
        read_pairs_file(f, NAMES)
    with pytest.raises(InputError, match="not found"):
        read_pairs_file(tmp_path / "missing.txt", NAMES)
    f.write_bytes(b"\xff\xfe bad")
    with pytest.raises(InputError, match="UTF-8"):
        read_pairs_file(f, NAMES)


def test_pairs_from_spec(tmp_path):
    names = NAMES[:6]
    assert len(pairs_from_spec("exhaustive", names)) == 15
    assert len(pairs_from_spec("sequential", names)) == 15  # K = 10 > n covers everything
    assert set(pairs_from_spec("sequential:2", names).pairs) == _colmap_sequential_reference(names, 2, False)
    assert set(pairs_from_spec("sequential:3:quadratic", names).pairs) == _colmap_sequential_reference(names, 3, True)
    f = tmp_path / "p.txt"
    f.write_text(f"{names[0]} {names[3]}\n")
    assert pairs_from_spec(str(f), names).pairs == ((names[0], names[3]),)
    with pytest.raises(ConfigError):
        pairs_from_spec("sequential:x", names)
    with pytest.raises(InputError, match="exhaustive"):
        pairs_from_spec("exhaustiv", names)
