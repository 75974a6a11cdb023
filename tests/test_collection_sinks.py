"""Match sinks: COLMAP database rows (pair order, pixel convention, atomicity, lock, read-only), hloc matches.h5."""
import os
import shutil
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from guidedmatch.collection.sinks import ColmapSink, H5MatchesSink, colmap_pixel_geometry, names_to_pair
from guidedmatch.collection.sources import ColmapSource, images_to_database
from guidedmatch.errors import ConfigError, DatabaseBusyError, DatabaseError, InputError, OutputError
from guidedmatch.geometry import TwoViewGeometry, two_view_geometry
from guidedmatch.matcher import match

SRC = os.path.join(os.path.dirname(__file__), os.pardir, "src")


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A 3-view COLMAP database (ours), the matches of views 0-1 and their two-view verdict."""
    from guidedmatch.testing.multiview import make_multiview, write_views

    mv = make_multiview(3, (320, 240), seed=5, isolated=False)
    root = tmp_path_factory.mktemp("sinkdb")
    write_views(mv, root / "img")
    src = images_to_database(root / "img", root / "db.db", max_features=800, progress=False)
    a, b = mv.names[0], mv.names[1]
    fa, fb = src.load(a), src.load(b)
    r = match(fa, fb)
    g = two_view_geometry(fa.keypoints[r.pairs[:, 0]], fb.keypoints[r.pairs[:, 1]], fa.image_size, fb.image_size)
    assert g and g.model == "F" and g.H is not None and g.num_inliers > 30  # both F and H rows get exercised
    return root / "db.db", mv, src, r, g


@pytest.fixture
def db_copy(base, tmp_path):
    path = tmp_path / "db.db"
    shutil.copy(base[0], path)
    return path


def _reversed(g: TwoViewGeometry) -> TwoViewGeometry:
    """The same verdict for the pair given the other way round (F^T, H^-1)."""
    return TwoViewGeometry(g.verdict, g.model, None if g.F is None else g.F.T,
                           None if g.H is None else np.linalg.inv(g.H), g.inliers, g.num_inliers, g.num_matches,
                           g.reason)


def _scaled_equal(A, B, tol=1e-6):
    A, B = A / np.linalg.norm(A), B / np.linalg.norm(B)
    return min(np.abs(A - B).max(), np.abs(A + B).max()) < tol


def test_colmap_round_trip(base, db_copy):
    _, mv, src, r, g = base
    a, b = mv.names[0], mv.names[1]
    with ColmapSink(db_copy) as sink:
        assert sink.done_pairs() == set()
        sink.write(a, b, r.pairs, r.distances, g)
        assert sink.done_pairs() == {frozenset((a, b))}
    db = pycolmap.Database.open(str(db_copy))
    i1, i2 = db.read_image_with_name(a).image_id, db.read_image_with_name(b).image_id
    assert i1 < i2
    assert np.array_equal(db.read_matches(i1, i2).astype(np.int64), r.pairs)
    tvg = db.read_two_view_geometry(i1, i2)
    assert int(tvg.config) == g.colmap_config
    assert np.array_equal(tvg.inlier_matches.astype(np.int64), r.pairs[g.inliers])
    kp1 = db.read_keypoints(i1)[:, :2].astype(float)
    kp2 = db.read_keypoints(i2)[:, :2].astype(float)
    db.close()
    # F in COLMAP pixels: the inliers' COLMAP keypoints satisfy it as ours satisfy g.F in OpenCV pixels
    x1 = np.c_[kp1[tvg.inlier_matches[:, 0]], np.ones(g.num_inliers)]
    x2 = np.c_[kp2[tvg.inlier_matches[:, 1]], np.ones(g.num_inliers)]
    l2 = x1 @ tvg.F.T
    d = np.abs(np.sum(x2 * l2, 1)) / np.hypot(l2[:, 0], l2[:, 1])
    assert np.median(d) < 1.0
    fa, fb = src.load(a), src.load(b)
    y1 = np.c_[fa.keypoints[r.pairs[g.inliers, 0]], np.ones(g.num_inliers)]
    y2 = np.c_[fb.keypoints[r.pairs[g.inliers, 1]], np.ones(g.num_inliers)]
    l2c = y1 @ g.F.T
    dc = np.abs(np.sum(y2 * l2c, 1)) / np.hypot(l2c[:, 0], l2c[:, 1])
    assert np.allclose(d, dc, atol=1e-3)  # float32 keypoints in the db
    assert _scaled_equal(tvg.H, colmap_pixel_geometry(None, g.H)[1])
    # the same matches as a planar verdict: config 6 (PLANAR_OR_PANORAMIC), H maps COLMAP pixels of the inliers
    gh = TwoViewGeometry("verified", "H", None, g.H, g.inliers, g.num_inliers, g.num_matches, "planar")
    with ColmapSink(db_copy) as sink:
        sink.write(b, a, r.pairs[:, ::-1], None, _reversed(gh))
    db = pycolmap.Database.open(str(db_copy))
    tvg = db.read_two_view_geometry(i1, i2)
    db.close()
    assert int(tvg.config) == 6 and tvg.F is None
    assert np.array_equal(tvg.inlier_matches.astype(np.int64), r.pairs[g.inliers])
    x1 = np.c_[kp1[tvg.inlier_matches[:, 0]], np.ones(g.num_inliers)] @ tvg.H.T
    fa, fb = src.load(a), src.load(b)
    y1 = np.c_[fa.keypoints[r.pairs[g.inliers, 0]], np.ones(g.num_inliers)] @ g.H.T
    assert np.allclose(x1[:, :2] / x1[:, 2:3] - 0.5, y1[:, :2] / y1[:, 2:3], atol=1e-3)


def test_colmap_reversed_pair_stored_canonically(base, db_copy, tmp_path):
    _, mv, _, r, g = base
    a, b = mv.names[0], mv.names[1]
    other = tmp_path / "other.db"
    shutil.copy(db_copy, other)
    with ColmapSink(db_copy) as sink:
        sink.write(a, b, r.pairs, None, g)
    with ColmapSink(other) as sink:
        sink.write(b, a, r.pairs[:, ::-1], None, _reversed(g))
        assert sink.done_pairs() == {frozenset((a, b))}
    rows = []
    for path in (db_copy, other):
        db = pycolmap.Database.open(str(path))
        i1, i2 = db.read_image_with_name(a).image_id, db.read_image_with_name(b).image_id
        rows.append((db.read_matches(i1, i2), db.read_two_view_geometry(i1, i2)))
        db.close()
    (m1, t1), (m2, t2) = rows
    assert np.array_equal(m1, m2) and np.array_equal(t1.inlier_matches, t2.inlier_matches)
    assert t1.config == t2.config
    for M1, M2 in ((t1.F, t2.F), (t1.H, t2.H)):
        assert (M1 is None) == (M2 is None)
        if M1 is not None:
            assert _scaled_equal(M1, M2)


@settings(max_examples=40, deadline=None)
@given(M=arrays(np.float64, (3, 3), elements=st.floats(-2, 2)),
       p=arrays(np.float64, (5, 2), elements=st.floats(0, 500)), swap=st.booleans())
def test_colmap_pixel_geometry(M, p, swap):
    """H and F converted to COLMAP pixels act on x + 0.5 as the originals act on x (and swap = other order)."""
    H = M + np.diag([3.0, 3.0, 3.0])  # well conditioned
    x1 = np.c_[p, np.ones(5)]
    y = x1 @ H.T
    if np.any(np.abs(y[:, 2]) < 1e-3):
        return
    x2 = y / y[:, 2:3]
    off = np.array([0.5, 0.5, 0.0])
    Fc, Hc = colmap_pixel_geometry(M, H, swap)
    if swap:  # stored for the pair (2, 1): maps image-2 COLMAP pixels to image-1 ones
        z = (x2 + off) @ Hc.T
        assert np.allclose(z[:, :2] / z[:, 2:3], (x1 + off)[:, :2], atol=1e-6 * (1 + np.abs(x1).max()))
        assert np.allclose(np.einsum("ij,jk,ik->i", x1 + off, Fc, x2 + off), np.einsum("ij,jk,ik->i", x2, M, x1))
    else:
        z = (x1 + off) @ Hc.T
        assert np.allclose(z[:, :2] / z[:, 2:3], (x2 + off)[:, :2], atol=1e-6 * (1 + np.abs(x2).max()))
        assert np.allclose(np.einsum("ij,jk,ik->i", x2 + off, Fc, x1 + off), np.einsum("ij,jk,ik->i", x2, M, x1))


def test_colmap_unverified_pair_and_resume(base, db_copy):
    _, mv, src, r, _ = base
    a, c = mv.names[0], mv.names[2]
    pairs = r.pairs[r.pairs[:, 1] < src.num_features(c)]  # some (wrong) matches, valid indices
    no = TwoViewGeometry("no-overlap", "none", None, None, np.zeros(len(pairs), bool), 0, len(pairs), "test")
    with ColmapSink(db_copy) as sink:
        sink.write(c, a, pairs[:, ::-1], None, no)
    with ColmapSink(db_copy) as sink:  # a new run sees the pair as done
        assert sink.done_pairs() == {frozenset((a, c))}
        assert sink.done_pairs([(a, c), (mv.names[1], a)]) == {frozenset((a, c))}
    b = mv.names[1]
    few = TwoViewGeometry("too-few-matches", "none", None, None, np.zeros(0, bool), 0, 0, "no matches")
    with ColmapSink(db_copy) as sink:
        sink.write(a, b, np.zeros((0, 2), np.int64), np.zeros(0, np.float32), few)
        assert sink.done_pairs() == {frozenset((a, b)), frozenset((a, c))}  # small db: exact, pair by pair
        assert sink.done_pairs([(b, a), (mv.names[1], c)]) == {frozenset((a, b))}
        sink.EXACT_PAIRS = 0  # pycolmap's bulk readers skip rows with 0 matches and no matrix (documented)
        assert sink.done_pairs() == {frozenset((a, c))}
    with ColmapSink(db_copy, overwrite=True) as sink:
        assert sink.done_pairs() == set()
    db = pycolmap.Database.open(str(db_copy))
    tvg = db.read_two_view_geometry(db.read_image_with_name(a).image_id, db.read_image_with_name(c).image_id)
    assert int(tvg.config) == 1 and len(tvg.inlier_matches) == 0 and tvg.F is None and tvg.H is None
    assert db.read_two_view_geometry_num_inliers() == ([], [])  # no pair with inliers for the mapper
    db.close()


def test_colmap_write_is_atomic(base, db_copy, monkeypatch):
    """An error between the matches row and the geometry row leaves neither (pycolmap commits on exit)."""
    _, mv, _, r, g = base
    a, b = mv.names[0], mv.names[1]

    def failing(db, i1, i2, m, tvg):
        db.write_matches(i1, i2, m)
        raise RuntimeError("simulated failure after the matches row")

    with ColmapSink(db_copy) as sink:
        monkeypatch.setattr(ColmapSink, "_write_rows", staticmethod(failing))
        with pytest.raises(RuntimeError, match="simulated"):
            sink.write(a, b, r.pairs, None, g)
        monkeypatch.undo()
        assert sink.done_pairs() == set()
    db = pycolmap.Database.open(str(db_copy))
    assert db.num_matches() == 0 and db.num_inlier_matches() == 0
    db.close()


def test_colmap_mode_colmap_then_verify(base, db_copy):
    _, mv, _, r, _ = base
    a, b = mv.names[0], mv.names[1]
    with ColmapSink(db_copy, geometry="colmap") as sink:
        sink.write(b, a, r.pairs[:, ::-1], None)
        assert sink.done_pairs() == {frozenset((a, b))}
        assert sink.verify({"min_num_inliers": 15}) == 1
        assert sink.verify() == 0  # nothing left without a geometry
    db = pycolmap.Database.open(str(db_copy))
    i1, i2 = db.read_image_with_name(a).image_id, db.read_image_with_name(b).image_id
    assert np.array_equal(db.read_matches(i1, i2).astype(np.int64), r.pairs)
    tvg = db.read_two_view_geometry(i1, i2)
    assert int(tvg.config) in (2, 3, 4, 5, 6) and len(tvg.inlier_matches) > 30
    db.close()
    with ColmapSink(db_copy, geometry="none") as sink, pytest.raises(ConfigError):
        sink.verify()


def test_colmap_bad_writes(base, db_copy):
    _, mv, _, r, g = base
    a, b = mv.names[0], mv.names[1]
    with ColmapSink(db_copy) as sink:
        with pytest.raises(InputError, match="not in COLMAP database"):
            sink.write(a, "ghost.png", r.pairs, None, g)
        with pytest.raises(InputError, match="out of range"):
            sink.write(a, b, r.pairs + 10_000, None, g)
        with pytest.raises(InputError, match="inliers"):
            sink.write(a, b, r.pairs[:-1], None, g)
        with pytest.raises(InputError, match="self-pair"):
            sink.write(a, a, r.pairs, None, g)
    with pytest.raises(ConfigError):
        ColmapSink(db_copy, geometry="maybe")
    with pytest.raises(DatabaseError, match="not found"):
        ColmapSink(db_copy.with_name("missing.db"))


def _run(code: str, *, user: int | None = None) -> subprocess.CompletedProcess:
    prelude = (f"import os, sys; sys.path.insert(0, {os.path.abspath(SRC)!r})\n"
               "import guidedmatch.collection, guidedmatch.validation, guidedmatch.errors\n")
    if user is not None:  # imports done as root (the interpreter may live where the user cannot read)
        prelude += f"os.setgid({user}); os.setuid({user})\n"
    return subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=120)


def test_lock_refuses_second_process(db_copy):
    code = f"""
        from guidedmatch.collection.sinks import ColmapSink
        from guidedmatch.errors import DatabaseBusyError
        try:
            ColmapSink({str(db_copy)!r})
        except DatabaseBusyError as e:
            print("BUSY", e)
        else:
            print("ACQUIRED")
    """
    with ColmapSink(db_copy):
        out = _run(code)
        assert out.stdout.startswith("BUSY") and f"pid {os.getpid()}" in out.stdout, out.stderr[-2000:]
        with pytest.raises(DatabaseBusyError):  # a second sink in the same process too
            ColmapSink(db_copy)
    assert _run(code).stdout.startswith("ACQUIRED")  # released on close


def test_read_only_database(db_copy, tmp_path):
    code = f"""
        from guidedmatch.collection.sinks import ColmapSink
        from guidedmatch.errors import OutputError
        try:
            ColmapSink({{path!r}})
        except OutputError as e:
            print("REFUSED", e)
        else:
            print("OPENED")
    """
    if os.geteuid() == 0:  # root ignores file modes: check as an unprivileged user in a world-readable folder
        import tempfile

        folder = tempfile.mkdtemp(prefix="gm-ro-", dir="/tmp")
        try:
            os.chmod(folder, 0o755)
            path = os.path.join(folder, "db.db")
            shutil.copy(db_copy, path)
            os.chmod(path, 0o444)
            out = _run(code.replace("{path!r}", repr(path)), user=65534)
            assert out.stdout.startswith("REFUSED") and "read-only" in out.stdout, out.stdout + out.stderr[-2000:]
            os.chmod(path, 0o666)
            os.chmod(folder, 0o555)
            out = _run(code.replace("{path!r}", repr(path)), user=65534)
            assert out.stdout.startswith("REFUSED") and "folder" in out.stdout, out.stdout + out.stderr[-2000:]
        finally:
            os.chmod(folder, 0o755)
            shutil.rmtree(folder)
    else:
        os.chmod(db_copy, 0o444)
        with pytest.raises(OutputError, match="read-only"):
            ColmapSink(db_copy)


# ---------------------------------------------------------------------------------------------------- hloc
def _hloc_get_matches(path, name0, name1):
    """hloc's reader (hloc/utils/io.py get_matches), restated: find either order, keep entries != -1."""
    with h5py.File(path, "r") as fh:
        for key, rev in ((names_to_pair(name0, name1), False), (names_to_pair(name1, name0), True)):
            if key in fh:
                m, s = fh[key]["matches0"][()], fh[key]["matching_scores0"][()]
                break
        else:
            raise KeyError((name0, name1))
    idx = np.nonzero(m != -1)[0]
    pairs = np.stack([idx, m[idx]], -1)
    return (pairs[:, ::-1] if rev else pairs), s[idx], m.dtype, len(m)


def _random_matches(rng, n1, n2, m):
    i1 = rng.choice(n1, size=m, replace=False)
    i2 = rng.choice(n2, size=m, replace=False)
    order = np.argsort(i1)
    return np.c_[i1[order], i2[order]].astype(np.int64), rng.uniform(0, 1, m).astype(np.float32)


def test_h5_round_trip_and_hloc_layout(tmp_path):
    rng = np.random.default_rng(0)
    nf = {"a.jpg": 50, "seq/b.jpg": 40_000, "c.jpg": 30}  # > 32,767 keypoints: needs int32
    written = {}
    with H5MatchesSink(tmp_path / "m.h5", nf, flush_every=2) as sink:
        for (x, y) in (("a.jpg", "seq/b.jpg"), ("seq/b.jpg", "c.jpg"), ("c.jpg", "a.jpg")):
            p, s = _random_matches(rng, nf[x], nf[y], 20)
            if y == "seq/b.jpg":
                p[0, 1] = 39_999
            sink.write(x, y, p, s)
            written[(x, y)] = (p, s)
        assert len(sink.done_pairs()) == 3
    assert not (tmp_path / "m.h5.parts").exists()
    with h5py.File(tmp_path / "m.h5") as fh:
        assert "a.jpg/seq-b.jpg" in fh and "seq-b.jpg/c.jpg" in fh  # hloc's names_to_pair keys
    for (x, y), (p, s) in written.items():
        got, gs, dtype, length = _hloc_get_matches(tmp_path / "m.h5", y, x)  # asked the other way round
        assert dtype == np.int32 and length == nf[x]
        assert np.array_equal(got[np.argsort(got[:, 1])], p[:, ::-1][np.argsort(p[:, 0])])
        assert np.allclose(np.sort(gs), np.sort(s))
    assert int(_hloc_get_matches(tmp_path / "m.h5", "a.jpg", "seq/b.jpg")[0][:, 1].max()) >= 32_768


def test_h5_resume_after_crash(tmp_path):
    rng = np.random.default_rng(1)
    nf = {f"{i}.png": 100 for i in range(6)}
    names = list(nf)
    sink = H5MatchesSink(tmp_path / "m.h5", nf, flush_every=2)
    for k in range(3):  # two flushed in a segment, the third only buffered
        sink.write(names[k], names[k + 1], *_random_matches(rng, 100, 100, 10))
    sink._lock.release()  # "crash": no close, no merge
    sink._closed = True
    assert not (tmp_path / "m.h5").exists()
    with H5MatchesSink(tmp_path / "m.h5", nf) as again:
        assert again.done_pairs() == {frozenset(names[0:2]), frozenset(names[1:3])}
        assert again.done_pairs([(names[2], names[1]), (names[4], names[5])]) == {frozenset(names[1:3])}
        p, s = _random_matches(rng, 100, 100, 10)
        again.write(names[3], names[2], p, s)
        again.write(names[1], names[0], p, s)  # the other order of a stored pair: replaces it
    with h5py.File(tmp_path / "m.h5") as fh:
        keys = set()
        fh.visititems(lambda n, o: keys.add(n) if isinstance(o, h5py.Group) and "matches0" in o else None)
    assert keys == {names_to_pair(names[1], names[2]), names_to_pair(names[3], names[2]),
                    names_to_pair(names[1], names[0])}
    got, _, _, _ = _hloc_get_matches(tmp_path / "m.h5", names[1], names[0])
    assert np.array_equal(got[np.argsort(got[:, 0])], p[np.argsort(p[:, 0])])


def test_h5_lock_and_bad_inputs(tmp_path):
    nf = {"a": 10, "b": 10}
    with H5MatchesSink(tmp_path / "m.h5", nf) as sink:
        with pytest.raises(DatabaseBusyError, match="another process"):
            H5MatchesSink(tmp_path / "m.h5", nf)
        with pytest.raises(InputError, match="not in the feature source"):
            sink.write("a", "zzz", np.zeros((0, 2), np.int64), None)
        with pytest.raises(InputError, match="one match per feature"):
            sink.write("a", "b", np.array([[1, 2], [1, 3]]), None)
        with pytest.raises(InputError, match="out of range"):
            sink.write("a", "b", np.array([[1, 10]]), None)
    (tmp_path / "x.h5").write_text("not hdf5")
    with pytest.raises(DatabaseError, match="not an HDF5"):
        H5MatchesSink(tmp_path / "x.h5")
    with H5MatchesSink(tmp_path / "free.h5") as sink:  # without a source: matches0 ends at the last match
        sink.write("a", "b", np.array([[3, 1]]), np.array([0.5]))
        assert sink.report["matches0_length"].startswith("last")
    assert _hloc_get_matches(tmp_path / "free.h5", "a", "b")[3] == 4


def test_h5_sink_from_source(base, tmp_path):
    _, mv, src, r, _ = base
    a, b = mv.names[0], mv.names[1]
    with H5MatchesSink(tmp_path / "m.h5", src) as sink:
        sink.write(a, b, r.pairs, 1.0 / (1.0 + r.distances))
    got, _, _, length = _hloc_get_matches(tmp_path / "m.h5", a, b)
    assert length == src.num_features(a) and np.array_equal(got, r.pairs[np.argsort(r.pairs[:, 0])])
    assert isinstance(src, ColmapSource)


def _synthetic_db(path, n_images=24, n_kp=200):
    db = pycolmap.Database.open(str(path))
    cid = db.write_camera(pycolmap.Camera.create_from_model_name(0, "PINHOLE", 100.0, 64, 48))
    rng = np.random.default_rng(0)
    for k in range(n_images):
        iid = db.write_image(pycolmap.Image(name=f"im{k:02d}.png", camera_id=cid))
        db.write_keypoints(iid, rng.uniform(0, 48, (n_kp, 2)).astype(np.float32))
        db.write_descriptors(iid, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                                              rng.integers(0, 255, (n_kp, 128), dtype=np.uint8)))
    db.close()


def test_colmap_sink_survives_kill_9(tmp_path):
    """kill -9 while a process writes pair after pair: every stored pair has both rows, consistent; resume works."""
    import signal

    path = tmp_path / "db.db"
    _synthetic_db(path)
    code = f"""
import numpy as np
from guidedmatch.collection.pairs import exhaustive_pairs
from guidedmatch.collection.sinks import ColmapSink
from guidedmatch.geometry import TwoViewGeometry
names = [f"im{{k:02d}}.png" for k in range(24)]
rng = np.random.default_rng(1)
with ColmapSink({str(path)!r}) as sink:
    for k, (a, b) in enumerate(exhaustive_pairs(names).pairs[::-1]):
        m = np.c_[rng.permutation(200)[:150], rng.permutation(200)[:150]]
        inl = rng.random(150) < 0.5
        g = TwoViewGeometry("verified", "F", rng.normal(size=(3, 3)), None, inl, int(inl.sum()), 150, "x")
        sink.write(a, b, m, None, g)
        print(k, flush=True)
"""
    proc = subprocess.Popen([sys.executable, "-c", f"import sys; sys.path.insert(0, {os.path.abspath(SRC)!r})\n"
                             + code], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        for _ in range(40):  # let it store ~40 pairs, then kill it mid-stream
            proc.stdout.readline()
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    db = pycolmap.Database.open(str(path))
    match_ids = set(db.read_num_matches()[0])
    geo_ids = set(db.read_two_view_geometry_num_inliers()[0])
    assert match_ids == geo_ids and len(match_ids) >= 40
    for pid in match_ids:
        i1, i2 = pycolmap.pair_id_to_image_pair(pid)
        m = {tuple(r) for r in db.read_matches(i1, i2)}
        inl = db.read_two_view_geometry(i1, i2).inlier_matches
        assert len(m) == 150 and {tuple(r) for r in inl} <= m and len(inl) > 0
    db.close()
    with ColmapSink(path) as sink:
        assert len(sink.done_pairs()) == len(match_ids)


def test_mapper_runs_on_our_geometry_without_verification(tmp_path):
    """Rendered collection -> our database -> matches + our two-view geometries -> pycolmap.incremental_mapping
    registers every view of the connected sequence; pairs without overlap get no inliers."""
    from guidedmatch.collection.pairs import exhaustive_pairs
    from guidedmatch.testing.multiview import make_multiview, write_views

    mv = make_multiview(seed=1)
    write_views(mv, tmp_path / "img")
    src = images_to_database(tmp_path / "img", tmp_path / "db.db", progress=False)
    with ColmapSink(tmp_path / "db.db") as sink:
        for a, b in exhaustive_pairs(src.names()):
            fa, fb = src.load(a), src.load(b)
            r = match(fa, fb)
            g = two_view_geometry(fa.keypoints[r.pairs[:, 0]], fb.keypoints[r.pairs[:, 1]], fa.image_size,
                                  fb.image_size)
            sink.write(a, b, r.pairs, r.distances, g)
    db = pycolmap.Database.open(str(tmp_path / "db.db"))
    with_inliers = {frozenset(map(int, pycolmap.pair_id_to_image_pair(p)))
                    for p in db.read_two_view_geometry_num_inliers()[0]}
    ids = {im.name: im.image_id for im in db.read_all_images()}
    db.close()
    for i, j in mv.non_overlapping_pairs():
        assert frozenset((ids[mv.names[i]], ids[mv.names[j]])) not in with_inliers
    recs = pycolmap.incremental_mapping(tmp_path / "db.db", tmp_path / "img", tmp_path / "sparse")
    assert len(recs) == 1
    rec = next(iter(recs.values()))
    registered = {im.name for im in rec.images.values() if im.has_pose}
    assert registered == set(mv.names) - {mv.names[k] for k in mv.isolated}


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), m=st.integers(0, 120), reverse=st.booleans(), model=st.sampled_from("FH"))
def test_colmap_rows_property(tmp_path_factory, seed, m, reverse, model):
    """Random matches / inliers / models written in either order read back in COLMAP's canonical form."""
    path = tmp_path_factory.mktemp("prop") / "db.db"
    _synthetic_db(path, n_images=3, n_kp=150)
    rng = np.random.default_rng(seed)
    pairs = np.c_[rng.permutation(150)[:m], rng.permutation(150)[:m]].astype(np.int64)  # (im00, im02)
    inl = rng.random(m) < 0.6
    F, H = rng.normal(size=(3, 3)), rng.normal(size=(3, 3)) + 3 * np.eye(3)
    g = TwoViewGeometry("verified", model, F if model == "F" else None, H, inl, int(inl.sum()), m, "x")
    with ColmapSink(path) as sink:
        if reverse:
            sink.write("im02.png", "im00.png", pairs[:, ::-1], None, _reversed(g))
        else:
            sink.write("im00.png", "im02.png", pairs, None, g)
    db = pycolmap.Database.open(str(path))
    i1, i2 = db.read_image_with_name("im00.png").image_id, db.read_image_with_name("im02.png").image_id
    assert np.array_equal(db.read_matches(i1, i2).astype(np.int64).reshape(-1, 2), pairs)
    tvg = db.read_two_view_geometry(i1, i2)
    db.close()
    assert int(tvg.config) == (3 if model == "F" else 6)
    assert np.array_equal(tvg.inlier_matches.astype(np.int64).reshape(-1, 2), pairs[inl])
    Fc, Hc = colmap_pixel_geometry(g.F, g.H)
    assert _scaled_equal(tvg.H, Hc, 1e-6)
    assert (tvg.F is None) == (model == "H") and (model == "H" or _scaled_equal(tvg.F, Fc, 1e-6))


@settings(max_examples=25, deadline=None)
@given(n1=st.integers(1, 300), n2=st.integers(1, 300), frac=st.floats(0, 1), seed=st.integers(0, 2**31))
def test_h5_rows_property(tmp_path_factory, n1, n2, frac, seed):
    rng = np.random.default_rng(seed)
    m = int(frac * min(n1, n2))
    p, s = _random_matches(rng, n1, n2, m)
    path = tmp_path_factory.mktemp("h5prop") / "m.h5"
    with H5MatchesSink(path, {"x/1.jpg": n1, "y.jpg": n2}) as sink:
        sink.write("x/1.jpg", "y.jpg", p, s)
    got, gs, dtype, length = _hloc_get_matches(path, "x/1.jpg", "y.jpg")
    assert length == n1 and dtype == np.int32
    assert np.array_equal(got, p) and np.array_equal(gs, s)


# --------------------------------------------------------------------------- capping the mapper's inliers
def _geometry_rows(path):
    db = pycolmap.Database.open(str(path))
    try:
        out = {}
        for pid in db.read_two_view_geometry_num_inliers()[0]:
            i1, i2 = pycolmap.pair_id_to_image_pair(int(pid))
            g = db.read_two_view_geometry(i1, i2)
            out[(i1, i2)] = (int(g.config), np.array(g.F), np.asarray(g.inlier_matches).copy(),
                             np.asarray(db.read_matches(i1, i2)).copy())
        return out
    finally:
        db.close()


def _slow_model_error(kp1, kp2, g, m):
    """Each correspondence's error to a geometry row's own model, one at a time: the Sampson distance to its F, for a
    planar row (configuration 4-6) the smaller of that and its H transfer error; None when the row has no model."""
    F = np.asarray(g.F, np.float64) if g.F is not None and np.any(g.F) else None
    H = np.asarray(g.H, np.float64) if int(g.config) in (4, 5, 6) and g.H is not None and np.any(g.H) else None
    if F is None and H is None:
        return None
    errs = []
    for a, b in m:
        x1, x2 = np.r_[kp1[a], 1.0], np.r_[kp2[b], 1.0]
        e = np.inf
        if F is not None:
            l2, l1 = F @ x1, F.T @ x2
            e = abs(float(x2 @ F @ x1)) / np.sqrt(l2[0] ** 2 + l2[1] ** 2 + l1[0] ** 2 + l1[1] ** 2)
        if H is not None:
            y = H @ x1
            e = min(e, float(np.hypot(y[0] / y[2] - x2[0], y[1] / y[2] - x2[1])))
        errs.append(e)
    return np.array(errs)


def _cap_reference(path, i1, i2, inliers, k, grid=16, order="distance", px=1.5):
    """The kept inliers computed independently from the raw database rows, then the rounds of the spread reference:
    ``distance`` -- L2 (SIFT) or Hamming (binary) descriptor distances; ``residual`` -- the error to the row's own
    model; ``track`` -- first the number of verified rows (of the whole database) whose raw matches use each of
    the match's two keypoints within ``px`` of the row's model (counted one row and one keypoint at a time), then
    that error."""
    from tests.test_geometry import _spread_reference

    db = pycolmap.Database.open(str(path))
    try:
        kps = {int(im.image_id): np.asarray(db.read_keypoints(im.image_id))[:, :2].astype(np.float64)
               for im in db.read_all_images()}
        d1, d2 = (np.asarray(db.read_descriptors(i).data) for i in (i1, i2))
        cam = db.read_camera(db.read_image(i1).camera_id)
        binary = db.read_descriptors(i1).type.name != "SIFT"
        g = db.read_two_view_geometry(i1, i2)
        used = {}   # (image id, keypoint) -> verified rows using it
        if order == "track":
            for pid, n in zip(*db.read_two_view_geometry_num_inliers()):
                if n == 0:
                    continue
                a, b = (int(i) for i in pycolmap.pair_id_to_image_pair(int(pid)))
                raw = np.asarray(db.read_matches(a, b)).tolist()
                e = _slow_model_error(kps[a], kps[b], db.read_two_view_geometry(a, b), raw)
                seen = {(a, p) for (p, q), ee in zip(raw, e) if ee <= px} | {(b, q) for (p, q), ee in zip(raw, e)
                                                                           if ee <= px}
                for key in seen:
                    used[key] = used.get(key, 0) + 1
    finally:
        db.close()
    a, b = d1[inliers[:, 0]], d2[inliers[:, 1]]
    if binary:
        dist = np.array([bin(int.from_bytes((x ^ y).tobytes(), "big")).count("1") for x, y in zip(a, b)], float)
    else:
        dist = np.sqrt(((a.astype(np.float64) - b.astype(np.float64)) ** 2).sum(1))
    if order == "distance":
        score = dist
    else:
        score = _slow_model_error(kps[i1], kps[i2], g, inliers.tolist())
        if order == "track":
            score = np.array([-(used.get((i1, p), 0) + used.get((i2, q), 0)) + min(e, 9.99) / 10
                              for (p, q), e in zip(inliers.tolist(), score)])
    keep = _spread_reference(kps[i1][inliers[:, 0]], (cam.width, cam.height), score, k, grid)
    return inliers[np.sort(keep)]


def _three_view_database(tmp_path, detector):
    from guidedmatch.testing.multiview import make_multiview, write_views

    mv = make_multiview(3, (320, 240), seed=5, isolated=False)
    write_views(mv, tmp_path / "img")
    src = images_to_database(tmp_path / "img", tmp_path / "db.db", detector=detector, max_features=800,
                             progress=False)
    with ColmapSink(tmp_path / "db.db") as sink:
        for a, b in ((0, 1), (0, 2), (1, 2)):
            fa, fb = src.load(mv.names[a]), src.load(mv.names[b])
            r = match(fa, fb)
            sink.write(mv.names[a], mv.names[b], r.pairs, r.distances, r.geometry)
    src.close()
    return tmp_path / "db.db"


@pytest.mark.parametrize("detector, order", [("sift", "track"), ("sift", "residual"), ("sift", "distance"),
                                             ("orb", "track"), ("orb", "distance")])
def test_cap_inliers_keeps_a_spread_best_first_subset(tmp_path, detector, order):
    """Pairs above the cap keep exactly the reference's inliers (a subset of theirs; config, F and the raw matches
    unchanged); pairs at or below it are untouched; a second pass changes nothing."""
    from guidedmatch.collection.sinks import cap_two_view_inliers

    db = _three_view_database(tmp_path, detector)
    before = _geometry_rows(db)
    counts = sorted(len(v[2]) for v in before.values())
    assert counts[0] > 20, counts
    k = counts[-1] - max(1, (counts[-1] - counts[0]) // 2)   # pairs above the cap (and, unless all are equal, below)
    rep = cap_two_view_inliers(db, k, order=order)
    after = _geometry_rows(db)
    assert rep["order"] == order
    assert rep["pairs_capped"] == sum(c > k for c in counts) >= 1
    assert rep["inliers_before"] == sum(counts) and rep["inliers_after"] == sum(min(c, k) for c in counts)
    for key, (config, F, inl, raw) in before.items():
        c2, F2, inl2, raw2 = after[key]
        assert c2 == config and np.allclose(F2, F) and np.array_equal(raw2, raw)
        if len(inl) <= k:
            assert np.array_equal(inl2, inl)
        else:
            assert len(inl2) == k
            assert np.array_equal(inl2, _cap_reference(db, *key, inl, k, order=order))
    assert cap_two_view_inliers(db, k, order=order)["pairs_capped"] == 0
    assert all(np.array_equal(after[key][2], v[2]) for key, v in _geometry_rows(db).items())


def test_cap_inliers_above_applies_only_to_a_larger_total(tmp_path):
    """``above``: at or below the database's total inliers nothing changes and the record says so (not applied, the
    total before and after); one inlier fewer and it is the plain cap, row for row."""
    import shutil

    from guidedmatch.collection.sinks import cap_two_view_inliers

    db = _three_view_database(tmp_path, "sift")
    before = _geometry_rows(db)
    counts = sorted(len(v[2]) for v in before.values())
    total, k = sum(counts), counts[0] - 5    # every pair above k
    for name in ("plain.db", "below.db"):
        shutil.copyfile(db, tmp_path / name)
    rep = cap_two_view_inliers(db, k, above=total)
    assert rep["applied"] is False and rep["above"] == total and rep["pairs_capped"] == 0
    assert rep["inliers_before"] == rep["inliers_after"] == total and rep["pairs"] == len(counts)
    assert all(np.array_equal(_geometry_rows(db)[key][2], v[2]) for key, v in before.items())
    capped = cap_two_view_inliers(tmp_path / "below.db", k, above=total - 1)
    plain = cap_two_view_inliers(tmp_path / "plain.db", k)
    assert capped["applied"] is True and plain["applied"] is True and capped["above"] == total - 1
    assert capped["pairs_capped"] == plain["pairs_capped"] == len(counts)
    a, b = _geometry_rows(tmp_path / "below.db"), _geometry_rows(tmp_path / "plain.db")
    assert all(np.array_equal(a[key][2], b[key][2]) for key in a)
    with pytest.raises(ConfigError, match="above"):
        cap_two_view_inliers(db, k, above=-1)


def test_cap_inliers_track_order_is_the_same_after_an_interrupted_pass(tmp_path):
    """The track order ranks by what the cap never changes: a pass interrupted after its first capped pair (that
    pair written, the others not), then run again, gives the database of one uninterrupted pass -- and the orders
    differ here, so the test can tell them apart."""
    import shutil

    from guidedmatch.collection.sinks import cap_two_view_inliers

    db = _three_view_database(tmp_path, "sift")
    counts = sorted(len(v[2]) for v in _geometry_rows(db).values())
    k = counts[0] - 5     # every pair capped
    for name in ("whole.db", "interrupted.db", "distance.db"):
        shutil.copyfile(db, tmp_path / name)
    cap_two_view_inliers(tmp_path / "whole.db", k)
    cap_two_view_inliers(tmp_path / "distance.db", k, order="distance")
    whole, by_distance = _geometry_rows(tmp_path / "whole.db"), _geometry_rows(tmp_path / "distance.db")
    assert any(not np.array_equal(whole[key][2], by_distance[key][2]) for key in whole)
    first = min(whole)
    d = pycolmap.Database.open(str(tmp_path / "interrupted.db"))
    try:
        g = d.read_two_view_geometry(*first)
        g.inlier_matches = np.ascontiguousarray(whole[first][2], dtype=np.uint32)
        d.update_two_view_geometry(*first, g)
    finally:
        d.close()
    rep = cap_two_view_inliers(tmp_path / "interrupted.db", k)
    assert rep["pairs_capped"] == len(whole) - 1
    again = _geometry_rows(tmp_path / "interrupted.db")
    assert all(np.array_equal(again[key][2], whole[key][2]) for key in whole)


def test_cap_inliers_bad_input_and_lock(db_copy):
    from guidedmatch.collection.sinks import cap_two_view_inliers

    with pytest.raises(ConfigError):
        cap_two_view_inliers(db_copy, 0)
    with pytest.raises(ConfigError, match="order"):
        cap_two_view_inliers(db_copy, 10, order="best")
    with ColmapSink(db_copy):
        with pytest.raises(DatabaseBusyError):
            cap_two_view_inliers(db_copy, 10)
    sink = ColmapSink(db_copy)
    sink.close()
    with pytest.raises(OutputError):
        sink.cap_inliers(10)


def _tighten_reference(path, key, config, F, H, inl, px, min_keep):
    """The inliers tightening keeps, computed slowly: each correspondence's Sampson distance to the row's F (or
    transfer error of its H for a planar row, or its Sampson distance to the row's F when smaller) one at a time
    from the raw COLMAP keypoints, then a plain sort."""
    db = pycolmap.Database.open(str(path))
    try:
        kp1, kp2 = (np.asarray(db.read_keypoints(i))[:, :2].astype(np.float64) for i in key)
    finally:
        db.close()
    errs = []
    for a, b in inl:
        x1, x2 = np.r_[kp1[a], 1.0], np.r_[kp2[b], 1.0]
        sampson = None
        if F is not None and np.any(F):
            l2, l1 = F @ x1, F.T @ x2
            sampson = abs(float(x2 @ F @ x1)) / np.sqrt(l2[0] ** 2 + l2[1] ** 2 + l1[0] ** 2 + l1[1] ** 2)
        if config in (4, 5, 6):
            y = H @ x1
            transfer = float(np.hypot(y[0] / y[2] - x2[0], y[1] / y[2] - x2[1]))
            errs.append(transfer if sampson is None else min(transfer, sampson))
        else:
            errs.append(sampson)
    if len(inl) <= min_keep:
        return inl
    within = [k for k, e in enumerate(errs) if e <= px]
    if len(within) < min_keep:
        within = sorted(sorted(range(len(errs)), key=lambda k: (errs[k], k))[:min_keep])
    return inl[within]


@pytest.mark.parametrize("px, planar_F", [(0.5, False), (1.5, False), (0.5, True)])
def test_tighten_inliers_keeps_those_within_px_of_the_rows_model(tmp_path, px, planar_F):
    """Every row keeps exactly the reference's inliers: within px of its own F (Sampson, COLMAP pixels) or, for a
    planar row, of its H or its F; at least 15; rows of at most 15 untouched; config, F, H and the raw matches unchanged; a
    second pass changes nothing."""
    from guidedmatch.collection.sinks import tighten_two_view_inliers
    from guidedmatch.testing.multiview import make_multiview, write_views

    mv = make_multiview(3, (320, 240), seed=5, isolated=False)
    write_views(mv, tmp_path / "img")
    src = images_to_database(tmp_path / "img", tmp_path / "db.db", detector="sift", max_features=800, progress=False)
    with ColmapSink(tmp_path / "db.db") as sink:
        for a, b in ((0, 1), (0, 2), (1, 2)):
            fa, fb = src.load(mv.names[a]), src.load(mv.names[b])
            r = match(fa, fb)
            g = r.geometry
            if (a, b) == (1, 2):   # one planar row: the same inliers judged by the verdict's H
                g = TwoViewGeometry("verified", "H", g.F if planar_F else None, g.H, g.inliers, g.num_inliers,
                                    g.num_matches, "planar")
            sink.write(mv.names[a], mv.names[b], r.pairs, r.distances, g)
    src.close()
    db = pycolmap.Database.open(str(tmp_path / "db.db"))
    full = {}
    for pid in db.read_two_view_geometry_num_inliers()[0]:
        i1, i2 = pycolmap.pair_id_to_image_pair(int(pid))
        g = db.read_two_view_geometry(i1, i2)
        full[(i1, i2)] = (int(g.config), None if g.F is None else np.array(g.F), None if g.H is None else np.array(g.H),
                          np.asarray(g.inlier_matches, dtype=np.int64).copy())
    db.close()
    assert sorted(v[0] for v in full.values()) == [3, 6]   # 0-2 do not overlap: one F row, one planar row
    before = _geometry_rows(tmp_path / "db.db")
    rep = tighten_two_view_inliers(tmp_path / "db.db", px)
    after = _geometry_rows(tmp_path / "db.db")
    expected = {key: _tighten_reference(tmp_path / "db.db", key, c, F, H, inl, px, 15)
                for key, (c, F, H, inl) in full.items()}
    for key, (config, F, inl, raw) in before.items():
        c2, F2, inl2, raw2 = after[key]
        assert c2 == config and np.array_equal(F2, F) and np.array_equal(raw2, raw)
        assert np.array_equal(inl2, expected[key]), key
    assert rep["inliers_before"] == sum(len(v[2]) for v in before.values())
    assert rep["inliers_after"] == sum(len(v) for v in expected.values())
    assert rep["pairs_tightened"] == sum(len(expected[k]) < len(before[k][2]) for k in before) >= 1
    assert tighten_two_view_inliers(tmp_path / "db.db", px)["pairs_tightened"] == 0
    assert all(np.array_equal(after[key][2], v[2]) for key, v in _geometry_rows(tmp_path / "db.db").items())


def test_tighten_inliers_on_a_scene_with_known_noise(tmp_path):
    """Synthetic correspondences of a known F, a third of them displaced 2-3 px off their epipolar line: tightening
    at 1.5 px keeps exactly the exact ones (and the floor keeps 15 of a pair whose inliers are all displaced)."""
    from guidedmatch.collection.sinks import tighten_two_view_inliers

    rng = np.random.default_rng(3)
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    R, t = pycolmap.Rotation3d(np.array([0.0, 0.1, 0.02])).matrix(), np.array([1.0, 0.05, 0.1])
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K).T @ tx @ R @ np.linalg.inv(K)
    n = 90
    X = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 8, n)]
    x1 = (K @ X.T).T
    x1 = x1[:, :2] / x1[:, 2:]
    x2 = (K @ (R @ X.T + t[:, None])).T
    x2 = x2[:, :2] / x2[:, 2:]
    off = np.arange(n) % 3 == 0
    line = (F @ np.c_[x1, np.ones(n)].T).T
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    x2 = x2 + off[:, None] * normal * rng.uniform(2.2, 3.0, n)[:, None] * 2   # ~2x the Sampson distance
    db = pycolmap.Database.open(str(tmp_path / "db.db"))
    cid = db.write_camera(pycolmap.Camera.create_from_model_name(0, "PINHOLE", 300.0, 320, 240))
    ids = [db.write_image(pycolmap.Image(name=f"{k}.png", camera_id=cid)) for k in range(4)]
    for iid, x in zip(ids, (x1, x2, x1, x2)):
        db.write_keypoints(iid, x.astype(np.float32))
    idx = np.c_[np.arange(n), np.arange(n)].astype(np.uint32)
    for (a, b), rows in (((0, 1), idx), ((2, 3), idx[off])):
        g = pycolmap.TwoViewGeometry()
        g.config, g.F, g.inlier_matches = 3, F, rows
        db.write_matches(ids[a], ids[b], rows)
        db.write_two_view_geometry(ids[a], ids[b], g)
    db.close()
    rep = tighten_two_view_inliers(tmp_path / "db.db", 1.5)
    rows = _geometry_rows(tmp_path / "db.db")
    assert np.array_equal(rows[(ids[0], ids[1])][2][:, 0], np.flatnonzero(~off))
    assert len(rows[(ids[2], ids[3])][2]) == 15 and rep["pairs_tightened"] == 2


def _two_view_db(path, pairs):
    """A COLMAP database with one PINHOLE camera (f 600, 640 x 480) and, per ``(x1, x2, F)`` of ``pairs``, two images
    whose keypoints are ``x1`` / ``x2`` and one F row (configuration 3) with every correspondence an inlier."""
    db = pycolmap.Database.open(str(path))
    cid = db.write_camera(pycolmap.Camera.create_from_model_name(0, "PINHOLE", 600.0, 640, 480))
    keys = []
    for k, (x1, x2, F) in enumerate(pairs):
        a, b = (db.write_image(pycolmap.Image(name=f"{k}_{j}.png", camera_id=cid)) for j in (0, 1))
        db.write_keypoints(a, np.asarray(x1, np.float32))
        db.write_keypoints(b, np.asarray(x2, np.float32))
        rows = np.c_[np.arange(len(x1)), np.arange(len(x1))].astype(np.uint32)
        g = pycolmap.TwoViewGeometry()
        g.config, g.F, g.inlier_matches = 3, F, rows
        db.write_matches(a, b, rows)
        db.write_two_view_geometry(a, b, g)
        keys.append((a, b) if a < b else (b, a))
    db.close()
    return keys


def _early_fit_pair(baseline_deg: float, seed: int):
    """Noisy correspondences (0.5 px) of a pair whose median triangulation angle is about ``baseline_deg``, and an
    "early" F: the 8-point fit of 12 of them -- what the verdict's first model update leaves at a small baseline."""
    import cv2

    from guidedmatch.epipolar import sampson_distance
    from guidedmatch.testing.twoview import general_pair

    depth = 6.0
    baseline = 2 * depth * np.tan(np.radians(baseline_deg) / 2)
    for k in range(50):
        s = general_pair(rng=seed * 100 + k, n_points=300, size=(640, 480), f1=600.0, f2=600.0, max_angle_deg=3,
                         baseline=baseline, depth=(5.0, 7.0), noise=0.5)
        Fe, _ = cv2.findFundamentalMat(s.x1n[:12], s.x2n[:12], cv2.FM_8POINT)
        if Fe is not None and Fe.shape == (3, 3):
            e = sampson_distance(Fe, s.x1n, s.x2n)
            if np.mean(e > 1.5) > 0.2:          # an early fit that leaves many precise inliers beyond 1.5 px
                return s, Fe
    raise AssertionError("no early fit far enough off")


def test_tighten_inliers_refits_small_baselines_only(tmp_path):
    """At a small baseline (~1 deg) the early F is fitted again on the inliers: the row's F is replaced, every kept
    inlier lies within 1.5 px of the new F (Sampson, recomputed here), more of the (0.5 px noise) correspondences
    survive than around the early F, and a rerun changes nothing; at a wide baseline (~12 deg) with an equally bad F
    the row is tightened around its own F, as with refit_below_deg=0."""
    from guidedmatch.collection.sinks import tighten_two_view_inliers
    from guidedmatch.epipolar import sampson_distance

    small, F_small = _early_fit_pair(1.0, 1)
    wide, F_wide = _early_fit_pair(12.0, 2)
    keys = _two_view_db(tmp_path / "db.db", [(small.x1n, small.x2n, F_small), (wide.x1n, wide.x2n, F_wide)])
    shutil.copyfile(tmp_path / "db.db", tmp_path / "plain.db")
    rep = tighten_two_view_inliers(tmp_path / "db.db", 1.5)
    assert rep["pairs_refit"] == 1 and rep["refit_below_deg"] == 3.0
    rows, plain_rep = _geometry_rows(tmp_path / "db.db"), tighten_two_view_inliers(tmp_path / "plain.db", 1.5,
                                                                                   refit_below_deg=0)
    plain = _geometry_rows(tmp_path / "plain.db")
    assert plain_rep["pairs_refit"] == 0
    (c, F, inl, _), (_, F_old, inl_old, _) = rows[keys[0]], plain[keys[0]]
    assert c == 3 and not np.allclose(F / np.linalg.norm(F), F_small / np.linalg.norm(F_small), atol=1e-6)
    assert np.all(sampson_distance(F, small.x1n[inl[:, 0]], small.x2n[inl[:, 1]]) <= 1.5 + 1e-3)
    assert len(inl) > len(inl_old) and len(inl) > 0.9 * len(small.x1n)
    assert np.array_equal(rows[keys[1]][2], plain[keys[1]][2]) and np.array_equal(rows[keys[1]][1], F_wide)
    again = tighten_two_view_inliers(tmp_path / "db.db", 1.5)
    assert again["pairs_refit"] == 0 and again["pairs_tightened"] == 0
    assert all(np.array_equal(rows[k][1], v[1]) and np.array_equal(rows[k][2], v[2])
               for k, v in _geometry_rows(tmp_path / "db.db").items())


def test_tighten_inliers_in_threads_writes_the_rows_of_one_thread(tmp_path, monkeypatch):
    """The rows' selections and refits in 3 threads, 2 rows per chunk (several chunks, a partial last one): the same
    database rows, counts and refits as in one thread -- small baselines (refit) and wide ones (tightened only)."""
    from guidedmatch.collection import sinks
    from guidedmatch.collection.sinks import tighten_two_view_inliers

    pairs = [(s.x1n, s.x2n, F) for s, F in (_early_fit_pair(deg, seed) for deg, seed in
                                           [(1.0, 3), (12.0, 4), (0.5, 5), (8.0, 6), (2.0, 7)])]
    _two_view_db(tmp_path / "one.db", pairs)
    shutil.copyfile(tmp_path / "one.db", tmp_path / "three.db")
    one = tighten_two_view_inliers(tmp_path / "one.db", 1.5, threads=1)
    chunked = sinks.ColmapSink._rewrite_inliers
    monkeypatch.setattr(sinks.ColmapSink, "_rewrite_inliers",
                        lambda self, *a, **k: chunked(self, *a, **dict(k, chunk=2)))
    three = tighten_two_view_inliers(tmp_path / "three.db", 1.5, threads=3)
    assert one["pairs_refit"] >= 2 and one["pairs_tightened"] == 5
    assert {k: v for k, v in one.items() if k != "time_s"} == {k: v for k, v in three.items() if k != "time_s"}
    a, b = _geometry_rows(tmp_path / "one.db"), _geometry_rows(tmp_path / "three.db")
    assert a.keys() == b.keys() and all(all(np.array_equal(x, y) for x, y in zip(a[k], b[k])) for k in a)
    with pytest.raises(ConfigError):
        tighten_two_view_inliers(tmp_path / "one.db", 1.5, threads=0)


def test_tighten_inliers_bad_input_and_lock(db_copy):
    from guidedmatch.collection.sinks import tighten_two_view_inliers

    for bad in (0, -1.0, float("nan")):
        with pytest.raises(ConfigError):
            tighten_two_view_inliers(db_copy, bad)
    with pytest.raises(ConfigError):
        tighten_two_view_inliers(db_copy, 1.5, min_inliers=-1)
    for bad in (-1, 181, float("nan")):
        with pytest.raises(ConfigError):
            tighten_two_view_inliers(db_copy, 1.5, refit_below_deg=bad)
    with ColmapSink(db_copy):
        with pytest.raises(DatabaseBusyError):
            tighten_two_view_inliers(db_copy, 1.5)


# ---------------------------------------------------------------------------------------------- full disk
class _Statvfs:
    """A filesystem with ``free`` bytes available (os.statvfs's fields the sinks read)."""

    def __init__(self, free):
        self.f_frsize, self.f_bavail = 4096, free // 4096


def test_colmap_sink_refuses_a_full_disk_before_the_transaction(db_copy, base, monkeypatch):
    """pycolmap commits a transaction in a C++ destructor: SQLite's "disk is full" there aborts the process
    (SIGABRT, found by the fault bench). The sink checks the space before each pair: OutputError naming the
    database; the pairs stored before stay complete and resumable. Opening it needs no space (a rerun with
    nothing left to write works on a full disk)."""
    import guidedmatch.collection.sinks as sinks

    _, mv, _, r, g = base
    real = os.statvfs
    monkeypatch.setattr(sinks.os, "statvfs", lambda p: _Statvfs(sinks.SPACE_MARGIN // 2))
    with ColmapSink(db_copy) as sink:
        with pytest.raises(OutputError, match=r"cannot write the COLMAP database .*db\.db: disk full: 4\.0 MB free"):
            sink.write(mv.names[0], mv.names[1], r.pairs, None, g)
        assert sink.done_pairs() == set()
    monkeypatch.setattr(sinks.os, "statvfs", real)
    with ColmapSink(db_copy) as sink:
        sink.write(mv.names[0], mv.names[1], r.pairs, None, g)
        monkeypatch.setattr(sinks.os, "statvfs", lambda p: _Statvfs(sinks.SPACE_MARGIN + 2 * r.pairs.nbytes))
        with pytest.raises(OutputError, match="disk full.*finished pairs are kept"):
            sink.write(mv.names[0], mv.names[2], r.pairs, None, g)
        monkeypatch.setattr(sinks.os, "statvfs", real)
        assert sink.done_pairs() == {frozenset(mv.names[:2])}


def test_colmap_sink_refuses_past_the_file_size_limit(db_copy):
    """``ulimit -f`` (RLIMIT_FSIZE): a write that could take the database past it is refused by name."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    sink = ColmapSink(db_copy)
    resource.setrlimit(resource.RLIMIT_FSIZE, (db_copy.stat().st_size + (1 << 20), hard))
    try:
        with pytest.raises(OutputError, match=r"db\.db.*file size limit: db\.db .* may not grow past"):
            sink.check_space()
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        sink.close()


def test_h5_sink_full_disk_is_an_output_error_and_resumes(tmp_path):
    """A segment that does not fit (here: the file size limit, EFBIG -- a full disk is ENOSPC, the same path) is
    an OutputError naming matches.h5; HDF5 never writes to the disk itself (it crashed the process when it did),
    no temp file is left, earlier segments stay and count as done; the merge is refused before it starts."""
    import resource

    rng = np.random.default_rng(3)
    nf = {f"{i}.png": 20_000 for i in range(5)}
    names = list(nf)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    sink = H5MatchesSink(tmp_path / "m.h5", nf, flush_every=1)
    sink.write(names[0], names[1], *_random_matches(rng, 20_000, 20_000, 50))   # one segment, ~160 KB
    resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, hard))
    try:
        with pytest.raises(OutputError, match=r"cannot write the matches file .*m\.h5 \(a segment"):
            sink.write(names[1], names[2], *_random_matches(rng, 20_000, 20_000, 50))
        assert not list((tmp_path / "m.h5.parts").glob("*.tmp"))
        sink._buffer.clear()
        with pytest.raises(OutputError, match=r"m\.h5: file size limit.*wait in"):
            sink.close()
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert not (tmp_path / "m.h5").exists() and len(list((tmp_path / "m.h5.parts").glob("*.h5"))) == 1
    with H5MatchesSink(tmp_path / "m.h5", nf) as again:
        assert again.done_pairs() == {frozenset(names[:2])}
    with h5py.File(tmp_path / "m.h5") as fh:
        assert names_to_pair(names[0], names[1]) in fh
