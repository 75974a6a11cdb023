"""CLI behaviour on bad input and first runs: strict reads, up-front checks, verdict, plots, JIT."""
import json

import cv2
import numpy as np
import pytest

from guidedmatch.cli import fallback_lines, main, read_matches


@pytest.fixture(scope="module")
def files(tmp_path_factory, small_scene):
    from guidedmatch.testing.scenes import make_scene

    d = tmp_path_factory.mktemp("robust")
    cv2.imwrite(str(d / "a.png"), small_scene.image1)
    cv2.imwrite(str(d / "b.jpg"), small_scene.image2, [cv2.IMWRITE_JPEG_QUALITY, 95])
    other = make_scene((640, 480), roll_deg=0.0, seed=11)  # different textures: no overlap with a.png
    cv2.imwrite(str(d / "other.png"), cv2.flip(other.image2, 1))
    data = (d / "b.jpg").read_bytes()
    (d / "cut.jpg").write_bytes(data[: int(len(data) * 0.3)])
    png = (d / "a.png").read_bytes()
    (d / "cut.png").write_bytes(png[: int(len(png) * 0.6)])
    (d / "afile").write_text("not a folder")
    return d


def _one_line_error(capsys, rc, *needles):
    out = capsys.readouterr()
    assert rc == 2, out.err
    assert out.err.startswith("guidedmatch: error:") and out.err.count("\n") == 1 and "Traceback" not in out.err
    for n in needles:
        assert n in out.err, out.err
    return out


@pytest.mark.parametrize("name", ["cut.jpg", "cut.png"])
def test_truncated_image_is_exit_2_naming_the_file(files, capsys, name):
    rc = main(["match", str(files / name), str(files / "a.png")])
    out = _one_line_error(capsys, rc, name, "truncated or corrupt")
    assert "features" not in out.out  # nothing was detected


@pytest.mark.parametrize("target,needle", [
    ("/proc/m.csv", "/proc/m.csv"),
    ("{d}/afile/m.npz", "afile/m.npz"),
    ("{d}/folder.npz", "is a folder"),
])
@pytest.mark.parametrize("flag", ["-o", "--plot"])
def test_unwritable_outputs_are_found_before_any_work(files, capsys, target, needle, flag):
    (files / "folder.npz").mkdir(exist_ok=True)
    (files / "folder.png").mkdir(exist_ok=True)
    target = target.format(d=files)
    if flag == "--plot":
        target = target.replace(".csv", ".png").replace(".npz", ".png")
        needle = needle.replace(".csv", ".png").replace(".npz", ".png")
    rc = main(["match", str(files / "a.png"), str(files / "b.jpg"), flag, target])
    out = _one_line_error(capsys, rc, needle)
    assert "features" not in out.out and ".tmp" not in out.err


def test_unwritable_folder_as_another_user(files):
    import os
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    tmp_path = Path(tempfile.mkdtemp(prefix="gm-ro-", dir="/tmp"))  # searchable by other users (pytest's is 0700)

    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        cmd = []
    else:  # root writes anywhere: run the check as nobody on a root-owned folder
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o755)
        tmp_path.chmod(0o755)
        cmd = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
        if subprocess.run(["which", "setpriv"], capture_output=True).returncode:
            pytest.skip("setpriv not available to drop root")
    code = ("from guidedmatch.features import check_output_path\n"
            f"check_output_path({str(ro / 'm.npz')!r}, '-o')")
    p = subprocess.run(cmd + [sys.executable, "-c", code], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    import shutil

    shutil.rmtree(tmp_path, ignore_errors=True)
    assert p.returncode != 0 and "OutputError: cannot write -o" in p.stderr and "does not accept new files" in p.stderr


def test_bad_detector_option_lists_the_valid_ones(files, capsys):
    rc = main(["match", str(files / "a.png"), str(files / "b.jpg"), "--detector-option", "contrastThreshold=abc"])
    out = _one_line_error(capsys, rc, "contrastThreshold must be a float; got 'abc'", "nOctaveLayers (int)")
    assert "features" not in out.out and "SIFT_create" not in out.err


def test_no_overlap_is_said_plainly_and_nothing_unverified_is_written(files, tmp_path, capsys):
    out = tmp_path / "m.csv"
    rc = main(["match", str(files / "a.png"), str(files / "other.png"), "-o", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    assert "no overlap: 0 geometrically verified matches" in text
    lines = out.read_text().splitlines()
    assert lines == ["i1,i2,x1,y1,x2,y2,distance"]
    rc = main(["match", str(files / "a.png"), str(files / "other.png"), "-o", str(tmp_path / "all.npz"),
               "--keep-unverified"])
    d = read_matches(tmp_path / "all.npz")
    assert rc == 0 and len(d["pairs"]) > 0 and not d["verified"].any()
    assert d["stats"]["geometry"]["verdict"] == "no-overlap"


def test_verified_pair_writes_exactly_the_inliers(files, tmp_path, capsys):
    rc = main(["match", str(files / "a.png"), str(files / "b.jpg"), "-o", str(tmp_path / "v.npz"),
               "--plot", str(tmp_path / "v.png")])
    text = capsys.readouterr().out
    assert rc == 0 and "verdict       : verified" in text
    d = read_matches(tmp_path / "v.npz")
    g = d["stats"]["geometry"]
    assert g["verdict"] == "verified" and len(d["pairs"]) == g["num_inliers"] > 50
    assert cv2.imread(str(tmp_path / "v.png")).shape[1] >= 1200  # both images side by side
    rc = main(["match", str(files / "a.png"), str(files / "b.jpg"), "-o", str(tmp_path / "all.json"),
               "--keep-unverified"])
    j = json.loads((tmp_path / "all.json").read_text())
    assert rc == 0 and sum(j["verified"]) == g["num_inliers"] and len(j["verified"]) == len(j["pairs"])


def test_max_image_size_option(files, tmp_path, capsys):
    rc = main(["match", str(files / "a.png"), str(files / "b.jpg"), "--max-image-size", "320", "-o",
               str(tmp_path / "s.npz")])
    text = capsys.readouterr().out
    assert rc == 0 and "long side <= 320 px" in text
    d = read_matches(tmp_path / "s.npz")
    assert d["keypoints1"][:, 0].max() > 320  # original pixels
    with pytest.raises(SystemExit) as e:
        main(["match", str(files / "a.png"), str(files / "b.jpg"), "--max-image-size", "0"])
    assert e.value.code == 2 and "positive integer" in capsys.readouterr().err


def test_memory_limit_is_a_clean_error_with_a_suggested_size(files, capsys, monkeypatch):
    import guidedmatch.features as F

    monkeypatch.setattr(F, "available_memory", lambda: 120 << 20)
    rc = main(["match", str(files / "a.png"), str(files / "b.jpg")])
    _one_line_error(capsys, rc, "--max-image-size", "a.png")


@pytest.mark.parametrize("bad", ["cut.jpg", "memory"])
def test_bad_input_on_a_first_run_is_one_line_before_any_compile_note(files, capsys, monkeypatch, bad):
    # on a cold Numba cache the helpers start (and the compile note prints) only after the images were read and
    # their detection memory checked: a corrupt or too large image is still exactly one error line
    import guidedmatch.features as F
    from guidedmatch import jit

    started = []
    monkeypatch.setattr(jit, "cache_is_cold", lambda detector: True)
    monkeypatch.setattr(jit, "_background_wanted", lambda: True)
    monkeypatch.setattr(jit, "_note_printed", False)
    monkeypatch.setattr(jit, "_start_helper", lambda detector, group: started.append(group))
    if bad == "memory":
        monkeypatch.setattr(F, "available_memory", lambda: 120 << 20)
        rc = main(["match", str(files / "a.png"), str(files / "b.jpg")])
        _one_line_error(capsys, rc, "--max-image-size", "a.png")
    else:
        rc = main(["match", str(files / "cut.jpg"), str(files / "a.png")])
        _one_line_error(capsys, rc, "cut.jpg", "truncated or corrupt")
    assert started == []


def test_keep_unverified_needs_output(files, capsys):
    rc = main(["match", str(files / "a.png"), str(files / "b.jpg"), "--keep-unverified"])
    _one_line_error(capsys, rc, "--keep-unverified needs -o")


def test_fallback_lines_count_repeats():
    fbs = [dict(what="focal1", reason="r")] * 3 + [dict(what="updates", reason="u")]
    assert fallback_lines(fbs) == ["focal1: r (x3)", "updates: u"]


def test_match_plot_is_readable_at_thousands_of_matches(tmp_path, rng):
    from guidedmatch import plots

    img = rng.integers(0, 255, (300, 400)).astype(np.uint8)
    p1 = rng.uniform(0, 400, (6000, 2)) * [1, 0.75]
    inl = rng.random(6000) < 0.8
    path = plots.match_pair(tmp_path / "m.png", img, img[:200], p1, p1 * 0.6, inl, "test")
    im = cv2.imread(str(path))
    assert im.shape[1] > 1200
    # both colours are present (inliers green, outliers red)
    b, g, r = (im[..., k].astype(int) for k in range(3))
    assert ((g > 150) & (r < 100)).sum() > 100 and ((r > 150) & (g < 100)).sum() > 100


def test_demo_panel_titles_do_not_overlap(tmp_path, monkeypatch, small_scene):
    from guidedmatch import plots

    figs = []
    orig = plots.save_figure
    monkeypatch.setattr(plots, "save_figure", lambda fig, path, dpi=110: (figs.append(fig), orig(fig, path, dpi))[1])
    pts = np.zeros((0, 2))
    panels = [dict(pts1=pts, pts2=pts, correct=np.zeros(0, bool),
                   title=f"mode {k}: 3431/3496 correct, 6.27 % comparisons and a long tail of words") for k in range(5)]
    plots.motion_field_panels(tmp_path / "d.png", small_scene.image1, panels, suptitle="guidedmatch demo: " + "x" * 120)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = figs[0]
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    axes = [ax for ax in fig.axes if ax.get_visible() and ax.axison]
    boxes = [ax.get_window_extent(r) for ax in axes] + [fig._suptitle.get_window_extent(r)]
    for ax in axes:
        t = ax.title.get_window_extent(r)
        for other in boxes:
            if other is not ax.get_window_extent(r):
                assert not t.overlaps(other) or other.bounds == ax.get_window_extent(r).bounds


def test_first_run_compilation_is_excluded_and_announced(small_scene_features, capsys):
    from numba import njit

    from guidedmatch import jit
    from guidedmatch.matcher import match

    @njit(cache=False)
    def fresh(x):
        return x + 1

    monkey_note = jit._note_printed
    jit._note_printed = False
    try:
        with jit.compile_monitor() as cm:
            fresh(1)
            fresh(2)
    finally:
        jit._note_printed = monkey_note or jit._note_printed
    assert cm.count == 1 and cm.seconds > 0
    assert capsys.readouterr().err.count("compiling Numba kernels") == 1
    f1, f2 = small_scene_features
    jit.warm_up(f1, f2, "so+epi+ia")
    with jit.compile_monitor() as cm:
        match(f1, f2, "so+epi+ia")
    assert cm.count == 0  # everything the run needs was compiled (or loaded) by the warm-up


# ------------------------------------------------------------------ CLI fuzz over corrupted image bytes
@pytest.fixture(scope="module")
def encoded_images(small_scene):
    img = cv2.resize(small_scene.image1, (160, 120), interpolation=cv2.INTER_AREA)
    return {ext: cv2.imencode(ext, img)[1].tobytes() for ext in (".jpg", ".png")}


def _mutate(data: bytes, op: str, pos: float, payload: bytes) -> bytes:
    i = int(pos * len(data))
    if op == "truncate":
        return data[:i]
    if op == "overwrite":
        return data[:i] + payload + data[i + len(payload):]
    if op == "insert":
        return data[:i] + payload + data[i:]
    if op == "delete":
        return data[:i] + data[i + max(1, len(payload)):]
    return payload + data[len(payload):]  # clobber the header


def test_cli_fuzz_corrupted_image_bytes_exit_0_or_2_without_traceback(encoded_images, files, tmp_path_factory):
    import contextlib
    import io

    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    d = tmp_path_factory.mktemp("fuzz")

    @settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
    @given(ext=st.sampled_from([".jpg", ".png"]), op=st.sampled_from(["truncate", "overwrite", "insert", "delete", "header"]),
           pos=st.floats(0, 1), payload=st.binary(min_size=0, max_size=64))
    def run(ext, op, pos, payload):
        path = d / f"x{ext}"
        path.write_bytes(_mutate(encoded_images[ext], op, pos, payload))
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(["match", str(path), str(files / "a.png"), "--mode", "so+epi+ia", "--max-features", "300"])
        text = err.getvalue()
        assert rc in (0, 2), (rc, text)
        assert "Traceback" not in text and "internal error" not in text
        if rc == 2:
            assert text.startswith("guidedmatch: error:") and text.count("\n") == 1, text

    run()


def test_match_reports_compilation_apart_from_time_s(small_scene_features, monkeypatch):
    import time as _time

    from guidedmatch import jit, matcher

    class Fake(jit.CompileMonitor):  # a run during which 5 s of compilation happened
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.seconds = 5.0

    import contextlib

    @contextlib.contextmanager
    def fake_monitor(note=True, stream=None):
        yield Fake(note=False)

    monkeypatch.setattr(matcher.run, "compile_monitor", fake_monitor)
    f1, f2 = small_scene_features
    t = _time.perf_counter()
    res = matcher.match(f1, f2, "so+epi+ia")
    wall = _time.perf_counter() - t
    assert wall < 5.0 and res.stats.details["jit_compile_s"] == 5.0 and res.stats.time_s == 0.0  # clamped at 0


def test_background_compile_never_leaves_helpers_running(monkeypatch):
    import subprocess
    import sys

    from guidedmatch import jit

    started = []

    def fake_start(detector, group):  # the helpers, run as harmless sleepers
        assert detector == "sift" and group in jit.HELPER_GROUPS
        p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(%s)" % (0.2 if ok else 60)])
        started.append(p)
        return p

    monkeypatch.setattr(jit, "_start_helper", fake_start)
    monkeypatch.setattr(jit, "_precompile", lambda detector, group: None)  # wait()'s in-process share
    monkeypatch.setattr(jit, "cache_is_cold", lambda detector: True)
    monkeypatch.setattr(jit, "_idle_cores", lambda: 2.0)
    monkeypatch.delenv(jit.BACKGROUND_ENV, raising=False)
    ok = True
    with jit.background_compile("sift", stream=sys.stdout) as bg:
        assert bg and len(bg.procs) == 2
    assert all(p.returncode == 0 for p in started)  # waited for on leaving the block
    ok, started[:] = False, []
    with pytest.raises(RuntimeError):
        with jit.background_compile("sift", stream=sys.stdout):
            raise RuntimeError("detection failed")
    assert len(started) == 2 and all(p.returncode is not None for p in started)  # killed, not left running
    ok, started[:] = True, []
    with jit.background_compile("sift", ("bf", "epi")) as bg:
        assert len(bg.procs) == 1  # no spatial-order mode: the "order" group is not compiled
    with jit.background_compile("sift", ("bf",)) as bg:
        assert not bg  # brute force alone: its one small kernel compiles in the foreground
    monkeypatch.setattr(jit, "_idle_cores", lambda: 0.3)  # saturated machine: forked helpers all the same ...
    monkeypatch.setattr(jit, "_can_fork", lambda: True)
    with jit.background_compile("sift") as bg:
        assert len(bg.procs) == 2
    monkeypatch.setattr(jit, "_can_fork", lambda: False)  # ... but no fresh interpreters: the foreground compiles
    with jit.background_compile("sift") as bg:
        assert not bg
    monkeypatch.setenv(jit.BACKGROUND_ENV, "1")  # ... unless asked for
    with jit.background_compile("sift") as bg:
        assert len(bg.procs) == 2
    monkeypatch.setattr(jit, "_idle_cores", lambda: 2.0)
    monkeypatch.setenv(jit.BACKGROUND_ENV, "0")
    with jit.background_compile("sift") as bg:
        assert not bg


def test_cache_is_cold_reads_the_numba_index():
    from guidedmatch import jit, kernels, matcher  # noqa: F401 - the matcher registers the cache probe with jit

    assert isinstance(jit.cache_is_cold("sift"), bool)
    assert jit._kernel_dtype("sift") == "uint8" and jit._kernel_dtype("orb") == "uint64"
    assert kernels._guided_ser._cache is not None  # the internals cache_is_cold reads exist in this Numba
