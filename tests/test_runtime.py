"""guidedmatch._runtime: the process-level start-up shortcuts, each checked in a fresh interpreter (they act once per
process, so the test process itself cannot show them)."""
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

_PROBE = textwrap.dedent("""
    import json, sys, threading
    import numpy as np
    from guidedmatch import _runtime, kernels
    if sys.argv[1] == "own":
        _runtime.mark_own_process()
    other = {}
    with _runtime.without_numba_blas_probe() as skipped:
        if sys.argv[2] == "thread":  # another thread may import SciPy meanwhile: hidden from the set-up thread only
            t = threading.Thread(target=lambda: other.update(ok=__import__("scipy.linalg") is not None))
            t.start(); t.join()
        order, offsets = kernels.counting_order(np.array([2, 0, 1, 0], np.int64), 3)
    import numba.np.arraymath as am
    hidden_after = any(isinstance(f, _runtime._HideScipy) for f in sys.meta_path)
    import scipy.linalg  # importable again after the block
    print(json.dumps(dict(skipped=skipped, have_blas=bool(am._HAVE_BLAS), order=order.tolist(),
                          offsets=offsets.tolist(), other=other.get("ok"), hidden_after=hidden_after)))
""")


def _probe(own: str, thread: str = "-") -> dict:
    r = subprocess.run([sys.executable, "-c", _PROBE, own, thread], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("thread", ["-", "thread"])
def test_own_process_skips_the_blas_probe_and_kernels_still_work(thread):
    out = _probe("own", thread)
    assert out["skipped"] is True
    assert out["order"] == [1, 3, 2, 0] and out["offsets"] == [0, 2, 3, 4]   # stable counting sort by key
    assert out["hidden_after"] is False
    if thread == "thread":
        # the other thread's import succeeded; SciPy is then loaded, so Numba's probe finds it (and costs nothing)
        assert out["other"] is True and out["have_blas"] is True
    else:
        assert out["have_blas"] is False


def test_a_library_process_keeps_numbas_blas_probe():
    out = _probe("library")
    assert out["skipped"] is False and out["have_blas"] is True
    assert out["order"] == [1, 3, 2, 0]


def test_numba_set_up_falls_back_when_hiding_scipy_breaks_it():
    """A Numba whose target set-up imported SciPy outside the BLAS probe would fail inside the block: the engine
    then sets Numba up again with SciPy visible (simulated: a block that raises ImportError first)."""
    code = textwrap.dedent("""
        import contextlib, json
        import numpy as np
        from guidedmatch import _runtime
        from guidedmatch.collection import worker
        _runtime.mark_own_process()

        @contextlib.contextmanager
        def broken():
            import numba.np.arraymath  # noqa: F401 - Numba's set-up starts ...
            raise ImportError("scipy.special hidden")  # ... and then needs SciPy
            yield

        worker.without_numba_blas_probe = broken
        worker._load_numba()
        from guidedmatch import kernels
        order, offsets = kernels.counting_order(np.array([1, 0], np.int64), 2)
        print(json.dumps(order.tolist()))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == [1, 0]


# --- pycolmap's exported zlib (_runtime.zlib_shadowed) ---------------------------------------------------------------
#: the raw hazard, without guidedmatch: pycolmap first, then a zlib stream (what a PNG writer does)
_ZLIB_RAW = "import pycolmap, zlib\nc = zlib.compressobj(6)\nc.compress(bytes(range(256)) * 4000)\nc.flush()\ndel c\n"


def _python(code: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=cwd)


def test_pycolmap_first_is_detected_exactly_when_zlib_would_abort(tmp_path):
    """Whatever this machine's pycolmap and system zlib do, guidedmatch's verdict agrees with it: a process that
    imported pycolmap first gets a warning at ``import guidedmatch`` and an OutputError from our writers exactly
    when a zlib stream would abort that process (it does with pycolmap 4.2.1 on Debian's zlib)."""
    pytest.importorskip("pycolmap")
    aborts = _python(_ZLIB_RAW, tmp_path).returncode != 0
    png, npz = tmp_path / "x.png", tmp_path / "x.npz"
    code = textwrap.dedent(f"""
        import pycolmap, json, warnings
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            import guidedmatch
        from guidedmatch._runtime import zlib_shadowed
        from guidedmatch.errors import OutputError
        out = dict(warned=any("zlib" in str(w.message) for w in caught), shadowed=zlib_shadowed() is not None,
                   errors=[])
        if out["shadowed"]:  # our writers refuse instead of aborting (without the check they would abort here)
            import numpy as np
            from guidedmatch.features import atomic_savez, atomic_write_text
            atomic_write_text({str(tmp_path / "x.txt")!r}, "plain text needs no zlib")
            from guidedmatch.plots import _plt, save_figure
            from guidedmatch.sfm import run_sfm
            for write in (lambda: save_figure(_plt().figure(), {str(png)!r}),
                          lambda: atomic_savez({str(npz)!r}, a=np.arange(3)),
                          lambda: run_sfm({str(tmp_path / "no-images")!r}, {str(tmp_path / "out")!r})):
                try:
                    write()
                except OutputError as exc:
                    out["errors"].append(str(exc))
        print(json.dumps(out))
    """)
    r = _python(code, tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["shadowed"] is aborts and out["warned"] is aborts
    if aborts:
        assert len(out["errors"]) == 3 and all("before pycolmap" in e for e in out["errors"])
        assert not png.exists() and not npz.exists() and not (tmp_path / "out").exists()  # sfm: before any work
        assert (tmp_path / "x.txt").read_text() == "plain text needs no zlib"


def test_importing_guidedmatch_first_keeps_zlib_usable_after_pycolmap(tmp_path):
    pytest.importorskip("pycolmap")
    code = "import guidedmatch\n" + _ZLIB_RAW + textwrap.dedent(f"""
        import numpy as np
        from guidedmatch._runtime import zlib_shadowed
        from guidedmatch.features import atomic_savez
        from guidedmatch.plots import _plt, save_figure
        save_figure(_plt().figure(), {str(tmp_path / "x.png")!r})
        atomic_savez({str(tmp_path / "x.npz")!r}, a=np.arange(3))
        print(zlib_shadowed())
    """)
    r = _python(code, tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "None"
    assert (tmp_path / "x.png").stat().st_size > 0 and np.load(tmp_path / "x.npz")["a"].tolist() == [0, 1, 2]


# --- faiss's bundled OpenBLAS: the CPU's kernels, chosen before faiss loads (_runtime.pin_faiss_blas) -------------

_BLAS_PROBE = textwrap.dedent("""
    import json, sys, warnings
    first = sys.argv[1]
    if first == "faiss":
        import faiss
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import guidedmatch
    from guidedmatch import _runtime
    import os
    blas = _runtime.faiss_blas()
    expected = _runtime.openblas_coretype(_runtime._cpu_flags(), os.uname().machine)
    print(json.dumps(dict(blas=blas, expected=expected, env=os.environ.get("OPENBLAS_CORETYPE"),
                          warned=[str(w.message) for w in caught if "OpenBLAS" in str(w.message)])))
""")


def _blas_probe(first: str = "guidedmatch", **env) -> dict:
    import os

    full = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "GUIDEDMATCH_FAISS_CORETYPE")}
    full.update(env)
    r = subprocess.run([sys.executable, "-c", _BLAS_PROBE, first], capture_output=True, text=True, timeout=300,
                       env=full)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="OPENBLAS_CORETYPE is pinned on Linux only")
def test_import_guidedmatch_pins_faiss_blas_to_the_cpus_kernels():
    out = _blas_probe()
    if out["expected"] is None:
        pytest.skip("this CPU has no AVX2 + FMA: OpenBLAS's own choice is kept")
    # faiss's OpenBLAS (0.3.15 in the 1.15.1 wheel) runs Prescott kernels on this project's AVX-512 Xeon by itself
    assert out["blas"]["pinned"] == out["expected"] == out["env"]
    assert str(out["blas"]["core"]).lower() == out["expected"].lower()
    assert out["blas"]["generic"] is False and out["warned"] == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="OPENBLAS_CORETYPE is pinned on Linux only")
def test_a_users_coretype_and_the_off_switch_are_respected():
    kept = _blas_probe(OPENBLAS_CORETYPE="Sandybridge")
    assert kept["env"] == "Sandybridge" and kept["blas"]["pinned"] is None
    assert kept["blas"]["why"] == "OPENBLAS_CORETYPE was already set"
    assert str(kept["blas"]["core"]).lower() == "sandybridge"
    off = _blas_probe(GUIDEDMATCH_FAISS_CORETYPE="off")
    assert off["env"] is None and off["blas"]["pinned"] is None and off["blas"]["why"] == "GUIDEDMATCH_FAISS_CORETYPE=off"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="OPENBLAS_CORETYPE is pinned on Linux only")
def test_faiss_imported_first_warns_exactly_when_its_kernels_are_generic():
    out = _blas_probe("faiss")
    assert out["env"] is None and out["blas"]["why"] == "faiss was imported before guidedmatch"
    assert bool(out["warned"]) == out["blas"]["generic"]
    if out["warned"]:
        assert out["blas"]["core"] in out["warned"][0]


@pytest.mark.parametrize("plain", [False, True])
def test_sigterm_after_pycolmap_ends_the_process_without_a_stack_dump_exactly_when_plain(plain):
    """pycolmap's import installs glog's SIGTERM handler (a ~20-line "*** SIGTERM received ... stack trace"):
    plain_sigterm() restores the default action -- the process ends by the signal, nothing printed."""
    code = textwrap.dedent(f"""
        import os, signal, time
        import pycolmap
        from guidedmatch import _runtime
        if {plain}:
            _runtime.plain_sigterm()
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == -15, (r.returncode, r.stderr[-2000:])
    assert ("SIGTERM" in r.stderr) != plain, r.stderr[-2000:]


def test_the_pycolmap_commands_end_quietly_on_sigterm(tmp_path):
    """`guidedmatch colmap` (one of PYCOLMAP_COMMANDS) stopped by SIGTERM mid-run, as a job scheduler or `timeout`
    does: it ends at once by the signal, with no stack dump, and the database holds only complete pairs."""
    import os
    import signal
    import time
    from pathlib import Path

    import pycolmap

    from guidedmatch.collection.sources import images_to_database
    from guidedmatch.testing.multiview import make_multiview, write_views

    mv = make_multiview(6, (320, 240), seed=5, isolated=False)
    write_views(mv, tmp_path / "img")
    images_to_database(tmp_path / "img", tmp_path / "db.db", detector="sift", max_features=800, progress=False)
    log = tmp_path / "log.jsonl"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    proc = subprocess.Popen([sys.executable, "-m", "guidedmatch.cli", "colmap", str(tmp_path / "db.db"),
                             "--workers", "0", "--threads", "1", "--log", str(log), "--no-progress"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if log.exists() and log.read_text().count('"event": "pair"') >= 1:
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == -15, (proc.returncode, err[-2000:])
    assert "SIGTERM" not in err and "stack trace" not in err, err[-2000:]
    db = pycolmap.Database.open(str(tmp_path / "db.db"))
    try:
        pids = {int(p) for p in db.read_num_matches()[0]}
        assert all(db.exists_two_view_geometry(*pycolmap.pair_id_to_image_pair(p)) for p in pids)
    finally:
        db.close()


@pytest.mark.parametrize("opt_out", [False, True])
def test_the_command_line_reexecutes_itself_with_huge_pages_exactly_when_they_apply(opt_out):
    """reexec_with_hugepages (what the CLI's main() does first when run as a program) starts the same command again
    with GLIBC_TUNABLES=glibc.malloc.hugetlb=1 where hugepage_env applies to this machine, and not at all with
    GUIDEDMATCH_HUGEPAGES=0 or where it does not apply; the arguments arrive unchanged."""
    import os

    from guidedmatch._runtime import hugepage_env

    code = ("import os, sys; from guidedmatch import _runtime; _runtime.reexec_with_hugepages(); "
            "print(os.environ.get('GLIBC_TUNABLES'), sys.argv[1:])")
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "GUIDEDMATCH_HUGEPAGES")}
    if opt_out:
        env["GUIDEDMATCH_HUGEPAGES"] = "0"
    r = subprocess.run([sys.executable, "-c", code, "a", "b c"], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    expected = None if opt_out or hugepage_env(env) is None else "glibc.malloc.hugetlb=1"
    assert r.stdout.strip() == f"{expected} ['a', 'b c']"


@pytest.mark.parametrize("argv, reexec", [(["colmap", "missing.db"], False), (["hloc", "f.h5", "p.txt", "m.h5"], False),
                                          (["extract", "no_such_folder", "db.db"], True)])
def test_only_commands_that_extract_features_start_again_with_huge_pages(monkeypatch, tmp_path, argv, reexec):
    """main() run as the program (argv from sys.argv) asks for the huge-page restart for a command that may extract
    features, never for colmap / hloc, which only match what a database or features file holds (a second start cost
    P8's matching 0.24 s for no measured gain); the command then runs as usual (here: exit 2, a missing input)."""
    from guidedmatch import cli

    calls = []
    monkeypatch.setattr(cli, "reexec_with_hugepages", lambda: calls.append(True))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["guidedmatch", *argv])
    assert cli.main() == 2
    assert calls == ([True] if reexec else [])


def test_hugepages_off_for_children_removes_only_the_tunable_the_restart_set(monkeypatch):
    """The tunable the restart set (hugepage_env marks it) leaves the environment that child processes inherit; a
    GLIBC_TUNABLES the user set, with or without the mark, stays."""
    import os

    from guidedmatch import _runtime

    env = _runtime.hugepage_env({}, thp_mode="always [madvise] never", glibc="glibc 2.36")
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    assert _runtime.hugepages_off_for_children() is True
    assert "GLIBC_TUNABLES" not in os.environ and _runtime._HUGEPAGES_OURS not in os.environ
    assert _runtime.hugepages_off_for_children() is False
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.hugetlb=1")      # the user's own
    assert _runtime.hugepages_off_for_children() is False and os.environ["GLIBC_TUNABLES"] == "glibc.malloc.hugetlb=1"
    monkeypatch.setenv(_runtime._HUGEPAGES_OURS, "glibc.malloc.hugetlb=1")
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.hugetlb=1:glibc.malloc.arena_max=2")   # changed since
    assert _runtime.hugepages_off_for_children() is False and "arena_max" in os.environ["GLIBC_TUNABLES"]
