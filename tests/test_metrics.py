import json
import os

import numpy as np
import pytest

from guidedmatch.datasets import EpipolarGT, HomographyGT
from guidedmatch.evaluation.meta import json_default, run_metadata, to_jsonable, write_json
from guidedmatch.evaluation.metrics import evaluate_matches, median_time, ransac_fundamental, summarize
from guidedmatch.results import MatchResult, MatchStats


def _result(pairs, comparisons=100, time_s=0.5, method="m"):
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return MatchResult(pairs, np.arange(len(pairs), dtype=np.float32),
                       MatchStats(method=method, comparisons=comparisons, time_s=time_s))


def test_evaluate_matches_on_hand_made_input():
    gt = HomographyGT(np.array([[1.0, 0, 10], [0, 1, 0], [0, 0, 1]]), (100, 100), (100, 100))
    kp1 = np.array([[5.0, 5], [20, 20], [50, 50], [90, 50], [30, 30]])
    kp2 = np.array([[15.0, 5], [30, 22.9], [60, 53.5], [99, 50], [0, 0]])
    # pair (0,0): exact; (1,1): 2.9 px; (2,2): 3.5 px -> wrong; (3,3): projection at x=100 is outside image 2;
    # (4,4): far off
    r = _result([[0, 0], [1, 1], [2, 2], [3, 3], [4, 4]])
    row = evaluate_matches(r, kp1, kp2, gt, pair="p", ransac=False)
    assert row == {"pair": "p", "method": "m", "n_features1": 5, "n_features2": 5, "comparisons": 100,
                   "matches": 5, "true_correspondences": 2, "precision": 0.4, "ransac_inliers": None,
                   "ransac_precision": None, "time_s": 0.5}
    # no GT, no matches, unknown comparisons
    empty = evaluate_matches(_result([], comparisons=None), kp1, kp2, None, method="flann")
    assert empty["matches"] == 0 and empty["precision"] is None and empty["comparisons"] is None
    assert empty["method"] == "flann"
    with pytest.raises(IndexError):
        evaluate_matches(_result([[0, 7]]), kp1, kp2, gt)


def test_summarize_sums_over_pairs_like_the_paper():
    rows = [
        {"pair": "a", "method": "bf", "n_features1": 10, "n_features2": 20, "comparisons": 200, "matches": 10,
         "true_correspondences": 5, "ransac_inliers": 6, "time_s": 1.0},
        {"pair": "b", "method": "bf", "n_features1": 30, "n_features2": 10, "comparisons": 300, "matches": 30,
         "true_correspondences": 25, "ransac_inliers": 24, "time_s": 3.0},
        {"pair": "a", "method": "flann", "n_features1": 10, "n_features2": 20, "comparisons": None, "matches": 4,
         "true_correspondences": 4, "ransac_inliers": None, "time_s": 0.1},
    ]
    s = {r["method"]: r for r in summarize(rows)}
    bf = s["bf"]
    assert (bf["n_pairs"], bf["comparisons"], bf["matches"], bf["true_correspondences"]) == (2, 500, 40, 30)
    assert bf["precision"] == pytest.approx(0.75)  # 30/40, not the mean of 0.5 and 0.833
    assert bf["ransac_precision"] == pytest.approx(0.75) and bf["time_s"] == pytest.approx(4.0)
    fl = s["flann"]
    assert fl["comparisons"] is None and fl["ransac_precision"] is None and fl["precision"] == 1.0
    by_pair = summarize(rows, by=("pair",))
    assert [r["pair"] for r in by_pair] == ["a", "b"] and by_pair[0]["comparisons"] is None


def _two_view(rng, n_in=300, n_out=100):
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    a = 0.2
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    t = np.array([-1.0, 0.1, 0.2])
    X = np.c_[rng.uniform(-3, 3, n_in), rng.uniform(-2, 2, n_in), rng.uniform(6, 15, n_in)]
    x1 = X @ K.T
    x2 = (X @ R.T + t) @ K.T
    p1, p2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:] + rng.normal(0, 0.3, (n_in, 2))
    o1, o2 = rng.uniform(0, 640, (n_out, 2)), rng.uniform(0, 480, (n_out, 2))
    return EpipolarGT.from_pose(K, K, R, t), np.r_[p1, o1], np.r_[p2, o2]


def test_ransac_precision_recovers_the_inlier_share(rng):
    gt, p1, p2 = _two_view(rng)
    n = len(p1)
    r = MatchResult(np.c_[np.arange(n), np.arange(n)], np.r_[np.zeros(300), np.ones(100)],
                    MatchStats(method="m", comparisons=n * n, time_s=0.0))
    row = evaluate_matches(r, p1, p2, gt, ransac=True)
    truth = gt.correct(p1, p2).mean()  # ~0.75 plus outliers that happen to fall near their epipolar line
    assert abs(row["ransac_precision"] - truth) < 0.03
    assert row["ransac_precision"] == row["ransac_inliers"] / n
    res = ransac_fundamental(p1, p2)
    assert res and res[1][:300].mean() > 0.97
    few = ransac_fundamental(p1[:5], p2[:5])
    assert not few and "fewer than 8" in few.reason
    row5 = evaluate_matches(MatchResult(np.c_[np.arange(5), np.arange(5)], np.zeros(5), MatchStats("m", 0, 0.0)), p1, p2, gt, ransac=True)
    assert row5["ransac_inliers"] == 0 and "fewer than 8" in row5["ransac_failure"]


def test_median_time():
    calls = []
    res, med, times = median_time(lambda: calls.append(1) or len(calls), repeats=5, warmup=2)
    assert res == 7 and len(times) == 5 and len(calls) == 7
    assert med == sorted(times)[2] and all(t >= 0 for t in times)
    with pytest.raises(ValueError):
        median_time(lambda: None, repeats=0)


def test_run_metadata_keys():
    m = run_metadata(seed=11)
    for k in ("git_commit", "git_dirty", "python", "numpy", "scipy", "cv2", "numba", "faiss", "cpu_model",
              "logical_cores", "numba_num_threads", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS",
              "OPENBLAS_NUM_THREADS", "platform", "timestamp_utc"):
        assert k in m
    assert m["seed"] == 11 and m["numpy"] == np.__version__ and m["logical_cores"] == os.cpu_count()
    assert m["timestamp_utc"].endswith("+00:00")
    assert set(m["faiss_blas"]) == {"core", "pinned", "why", "generic"}  # which kernels faiss's OpenBLAS ran
    # the widest SIMD extension, from the same flags the OpenBLAS pin reads (the time ratios depend on it)
    from guidedmatch._runtime import _cpu_flags
    from guidedmatch.evaluation.meta import cpu_vector

    assert m["cpu_vector"] == cpu_vector(_cpu_flags())
    assert m["cpu_vector"] in (None, "AVX-512", "AVX2", "AVX", "SSE4.2")
    json.dumps(m)  # plain JSON types only


def test_write_json_is_atomic_and_converts_numpy(tmp_path, monkeypatch):
    obj = {"i": np.int64(3), "f": np.float32(0.5), "b": np.bool_(True), "a": np.arange(3), "t": (1, 2),
           "nan": float("nan"), "inf": np.float64(np.inf), "p": tmp_path, 5: "int key"}
    path = write_json(tmp_path / "sub" / "out.json", obj)
    back = json.loads(path.read_text())
    assert back == {"i": 3, "f": 0.5, "b": True, "a": [0, 1, 2], "t": [1, 2], "nan": None, "inf": None,
                    "p": str(tmp_path), "5": "int key"}
    assert [p.name for p in path.parent.iterdir()] == ["out.json"]  # no temp file left
    assert (path.stat().st_mode & 0o777) != 0o600  # readable like a normal file
    # a write that fails before the rename leaves the previous file intact and no temp file behind
    import guidedmatch.features

    def boom(tmp, dst):
        raise OSError("disk full")

    monkeypatch.setattr(guidedmatch.features, "publish", boom)
    with pytest.raises(OSError):
        write_json(path, {"i": 4})
    assert json.loads(path.read_text())["i"] == 3
    assert [p.name for p in path.parent.iterdir()] == ["out.json"]
    assert json.dumps({"a": np.arange(2)}, default=json_default) == '{"a": [0, 1]}'
    assert to_jsonable({"x": [np.float64(np.nan)]}) == {"x": [None]}
