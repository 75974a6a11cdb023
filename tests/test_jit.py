"""guidedmatch.jit: first-run compilation in forked helpers, warm-up, which kernels a run needs."""
import os
import subprocess
import sys

import numpy as np
import pytest

import guidedmatch.matcher  # noqa: F401 - registers the matcher's warm-ups with guidedmatch.jit
from guidedmatch import jit
from guidedmatch.features import Features


def _features(n, binary=False, seed=0):
    rng = np.random.default_rng(seed)
    desc = rng.integers(0, 256, (n, 32 if binary else 128)).astype(np.uint8 if binary else np.float32)
    return Features.from_arrays(rng.uniform(0, 500, (n, 2)), desc, (500, 500))


@pytest.mark.parametrize("n, binary, modes, config, want", [
    (3000, False, ("so+epi+ia",), None, True),
    (3000, False, ("bf",), None, False),                          # brute force needs no guided kernel
    (1500, False, ("bf", "epi", "so"), None, False),             # sqrt(N1 N2) < bf_below_float: auto-bf
    (1500, False, ("epi",), dict(auto_bf=False), True),
    (10000, True, ("bf", "epi", "so", "so+epi", "so+epi+ia"), None, False),  # ORB demo: < bf_below_binary
    (10000, True, ("so",), dict(bf_below_binary=5000), True),
])
def test_guided_kernels_needed(n, binary, modes, config, want):
    f1, f2 = _features(n, binary, 1), _features(n, binary, 2)
    assert jit.guided_kernels_needed(f1, f2, modes, config) is want


def test_cancel_kills_the_helpers_and_reports_none(monkeypatch):
    started = []

    def fake_start(detector, group):
        p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
        started.append(p)
        return p

    monkeypatch.setattr(jit, "_start_helper", fake_start)
    monkeypatch.setattr(jit, "cache_is_cold", lambda detector: True)
    monkeypatch.setenv(jit.BACKGROUND_ENV, "1")
    with jit.background_compile("orb", stream=sys.stdout) as bg:
        assert bg.helpers == 2
        bg.cancel()
        assert not bg and bg.helpers == 0 and bg.wait() == 0.0
    assert len(started) == 2 and all(p.returncode is not None for p in started)  # killed, none left running


def test_forked_helpers_fill_the_cache_the_foreground_then_only_loads(tmp_path, small_scene_features):
    """A cold NUMBA_CACHE_DIR: the helper groups (forked, as on a first CLI run) plus the in-process "bf" group
    compile every kernel a SIFT so+epi+ia / so / epi / bf run needs -- the foreground warm-up compiles nothing."""
    f1, f2 = small_scene_features
    f1.save(tmp_path / "f1.npz")
    f2.save(tmp_path / "f2.npz")
    code = f"""
import sys
import guidedmatch.matcher
from guidedmatch import jit
from guidedmatch.features import Features
f1, f2 = Features.load({str(tmp_path / 'f1.npz')!r}), Features.load({str(tmp_path / 'f2.npz')!r})
assert jit.cache_is_cold("sift")
with jit.background_compile("sift", ("bf", "epi", "so", "so+epi", "so+epi+ia"), stream=sys.stdout) as bg:
    assert len(bg.procs) == 2 and all(type(p).__name__ == "_Forked" for p in bg.procs.values())
    bg.wait("guided")
    bg.wait()
    assert bg.helper_seconds > 0.5, bg.helper_seconds
assert not jit.cache_is_cold("sift")
total = 0.0
for mode in ("bf", "epi", "so", "so+epi", "so+epi+ia"):
    total += jit.warm_up(f1, f2, mode, dict(auto_bf=False), note=False)  # guided on these ~1k features too
print("FOREGROUND_COMPILE", total)
from guidedmatch import exact, kernels, strip_index
from guidedmatch.spatial_order import _kernels as so
print("USED", sorted(set(n for m in (exact, kernels, strip_index, so) for n, v in vars(m).items()
                         if getattr(v, "overloads", None))))
"""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "GUIDEDMATCH_BACKGROUND_COMPILE": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "FOREGROUND_COMPILE 0.0" in out.stdout, out.stdout
    used = out.stdout.split("USED")[1]
    for name in ("_guided_ser", "topk_gemm_serial", "_refine", "counting_order", "_gap_kernel",
                 "_refine_window_nb", "_sweep_kendall", "_inversions_dense", "_window_fit_gaussian",
                 "_strip_layout", "search_regions_kernel"):
        assert f"'{name}'" in used  # the warm-ups did reach (load) every kernel: the check above is not vacuous
    assert out.stdout.count("compiling Numba kernels") == 1




def test_warmups_are_a_registry_the_matcher_fills():
    """jit imports neither the matcher nor the kernels it warms up: the matcher registers every warm-up name at
    import, and an unknown name is refused."""
    import ast
    import inspect

    from guidedmatch.matcher import warmup

    assert set(jit._WARMUPS) == set(jit.WARMUP_NAMES)
    assert jit.registered_warmup("match") is warmup.warm_up_match
    with pytest.raises(ValueError, match="unknown warm-up name"):
        jit.register_warmup("nonsense", lambda: None)
    imported = set()
    for node in ast.walk(ast.parse(inspect.getsource(jit))):
        if isinstance(node, ast.ImportFrom):
            imported |= {f"{node.module or ''}.{a.name}".lstrip(".") for a in node.names} | {node.module or ""}
        elif isinstance(node, ast.Import):
            imported |= {a.name for a in node.names}
    assert not {m for m in imported if any(k in m for k in ("matcher", "kernels", "spatial_order"))}, imported


def test_registered_warmup_names_the_missing_registration(monkeypatch):
    monkeypatch.setattr(jit, "_WARMUPS", {})
    with pytest.raises(RuntimeError, match="import guidedmatch.matcher first"):
        jit.warm_up(_features(10), _features(10), "bf")
