import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from guidedmatch.results import FLAG_KEYS, CandidateStats, Fallback, MatchResult, MatchStats, ModelUpdate


def _stats(**kw):
    return MatchStats(method="m", comparisons=6, time_s=0.5, num_features=(2, 3), **kw)


def test_match_result_conventions_and_default_flags():
    r = MatchResult([[0, 1], [1, 2]], [1.5, 2.0], _stats())
    assert r.pairs.dtype == np.int64 and r.pairs.shape == (2, 2) and r.distances.dtype == np.float32
    assert tuple(r.flags) == FLAG_KEYS and r.geometry is None
    assert r.flags["phase"].tolist() == [0, 0] and r.flags["in_band"].all() and np.isnan(r.flags["so_prob"]).all()
    with pytest.raises(ValueError, match="differ in length"):
        MatchResult([[0, 1]], [1.0, 2.0], _stats())
    with pytest.raises(ValueError, match="flags\\['phase'\\] has 1 entries for 2"):
        MatchResult([[0, 1], [1, 2]], [1.0, 2.0], _stats(), {"phase": np.zeros(1, np.int64)})
    with pytest.raises(TypeError, match="must be a MatchStats"):
        MatchResult([[0, 1]], [1.0], {"comparisons": 1})


def test_stats_derived_values_item_access_and_json():
    s = _stats(updates=(ModelUpdate(1, 40, F_inliers=30, H2=np.eye(3)),), fallbacks=(Fallback("updates", "why", 1),),
               F=np.ones((3, 3)), details={"threads": 2})
    assert s.bf_comparisons == 6 and s.comparison_ratio == 1.0 and s.num_model_updates == 1
    assert s["comparisons"] == 6 and s["num_model_updates"] == 1 and s["threads"] == 2 and s.get("nope", 7) == 7
    with pytest.raises(KeyError):
        s["nope"]  # noqa: B018
    d = json.loads(json.dumps(s.to_dict(), allow_nan=False))
    assert d["updates"][0]["H2"] == np.eye(3).tolist() and d["fallbacks"][0] == {"what": "updates", "reason": "why",
                                                                              "at_update": 1}
    assert d["F"] == np.ones((3, 3)).tolist() and d["details"] == {"threads": 2} and d["comparison_ratio"] == 1.0
    assert MatchStats("flann", None, 0.1).to_dict()["comparison_ratio"] is None  # unknown comparisons: NaN -> null


@settings(max_examples=50, deadline=None)
@given(arrays(np.int64, st.integers(0, 50), elements=st.integers(0, 10_000)))
def test_candidate_stats_equal_numpy(n):
    c = CandidateStats.of(n)
    if len(n) == 0:
        assert c == CandidateStats()
        return
    assert (c.mean, c.max) == (pytest.approx(n.mean()), n.max())
    assert (c.p50, c.p90, c.p99) == tuple(pytest.approx(v) for v in np.percentile(n, [50, 90, 99]))
