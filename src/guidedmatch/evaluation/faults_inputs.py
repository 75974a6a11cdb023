"""Corrupt inputs and fuzzed argument lists for the fault-injection benchmark
(:mod:`guidedmatch.evaluation.bench_faults`) and its test.

Every case builds one bad input in a scratch folder and runs one ``guidedmatch`` command on it. Expected: exit 2
with a message naming the file and what is wrong -- or, for the inputs with a documented handling (a pairs file
repeating a pair, non-image files in an image folder, EXIF rotation, 16-bit images, unicode names), exit 0 -- and
never a traceback or an "internal error".
"""
from __future__ import annotations

import contextlib
import io
import shutil
import signal
import sqlite3
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GuidedMatchError
from .faults_common import Row, Run, run_cli


# ============================================================================================ in-process CLI
class _Timeout(BaseException):
    """Raised by the fuzzer's alarm (a BaseException: the CLI's error handlers do not catch it)."""


def run_inprocess(argv, timeout: float = 0) -> Run:
    """``guidedmatch.cli.main(argv)`` in this process: exit status (SystemExit included), stdout, stderr; an
    exception escaping ``main`` is written to stderr as a traceback (rc None). ``timeout`` s (main thread only):
    stopped, rc None, stderr ends with ``[timeout]``."""
    import importlib

    main = importlib.import_module("guidedmatch.cli").main  # the fuzzer's target; at call time, no import cycle

    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    old = None
    if timeout:
        def on_alarm(*_):
            raise _Timeout()
        old = signal.signal(signal.SIGALRM, on_alarm)
        signal.setitimer(signal.ITIMER_REAL, timeout)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = main([str(a) for a in argv])
            except SystemExit as exc:
                rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
            except _Timeout:
                rc = None
                err.write("\n[timeout]")
            except BaseException as exc:  # noqa: BLE001 - what the user would see as a traceback
                if isinstance(exc, GuidedMatchError) and "--debug" in [str(a) for a in argv]:
                    # --debug asks for the traceback of a user error: main re-raises it instead of exit 2 (documented)
                    rc = 2
                    err.write(f"guidedmatch: error (--debug: raised as asked): {exc}\n")
                else:
                    rc = None
                    err.write(traceback.format_exc())
    finally:
        if timeout:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
    return Run([str(a) for a in argv], rc, out.getvalue(), err.getvalue(), time.perf_counter() - t0)


# ============================================================================================ h5 helpers
def h5_pairs(path: Path) -> dict | None:
    """``{pair key: (matches0 bytes, scores bytes)}`` of a matches.h5 (None when it cannot be read)."""
    import h5py

    try:
        out = {}
        with h5py.File(path, "r") as fh:
            def visit(name, obj):
                if isinstance(obj, h5py.Group) and "matches0" in obj:
                    out[name] = (np.asarray(obj["matches0"]).tobytes(),
                                 np.asarray(obj["matching_scores0"]).tobytes() if "matching_scores0" in obj else b"")
            fh.visititems(visit)
        return out
    except Exception:  # noqa: BLE001 - any unreadable file
        return None


def make_features_h5(db: Path, path: Path) -> Path:
    """An hloc features.h5 with the features of a COLMAP database."""
    from ..collection.sources import ColmapSource, write_features_h5

    if not path.exists():
        with ColmapSource(db) as src:
            write_features_h5(path, {n: src.load(n) for n in src.names()})
    return path


def make_h5_reference(coll: dict, work: Path) -> dict:
    """features.h5 of the collection and the matches.h5 of an uninterrupted ``guidedmatch hloc`` run."""
    feats = make_features_h5(coll["db"], work / "features.h5")
    ref = work / "ref-matches.h5"
    if not ref.exists():
        run = run_cli(["hloc", feats, "exhaustive", ref, "--workers", "0", "--no-progress", "--log", "none"])
        if run.rc != 0:
            raise RuntimeError(f"the uninterrupted hloc run failed: {run.tail()}")
    return {"features": feats, "matches": ref, "pairs": h5_pairs(ref), "bytes": ref.stat().st_size}


# ============================================================================================ cases
@dataclass(frozen=True)
class Case:
    """One corrupt input: ``build(folder, env) -> (argv, the file the message must name)``; ``accept``: a regex
    the output must contain when exit 0 is the documented handling (None: exit 2 expected)."""

    group: str
    name: str
    build: object
    accept: str | None = None


def _copy_db(env: dict, folder: Path) -> Path:
    db = folder / "database.db"
    shutil.copy(env["db"], db)
    return db


def _sql(db: Path, *statements, params=()) -> None:
    con = sqlite3.connect(db)
    for s in statements:
        con.execute(s, params) if params else con.execute(s)
    con.commit()
    con.close()


def _db_case(mutate):
    def build(folder: Path, env: dict):
        db = _copy_db(env, folder)
        mutate(db)
        return ["colmap", db, "--workers", "0", "--no-progress", "--log", "none"], db
    return build


def _truncate(frac: float):
    def go(db: Path) -> None:
        data = db.read_bytes()
        db.write_bytes(data[:int(len(data) * frac)])
    return go


def _wrong_schema(db: Path) -> None:
    db.unlink()
    _sql(db, "CREATE TABLE photos (id INTEGER PRIMARY KEY, path TEXT)", "INSERT INTO photos VALUES (1, 'a.jpg')")


def _broken_table(db: Path) -> None:
    _sql(db, "DROP TABLE keypoints", "CREATE TABLE keypoints (image_id INTEGER PRIMARY KEY NOT NULL, x REAL)")


def _short_descriptor_blob(db: Path) -> None:
    _sql(db, "UPDATE descriptors SET data = substr(data, 1, length(data) - 7) WHERE image_id = 2")


def _short_keypoint_blob(db: Path) -> None:
    _sql(db, "UPDATE keypoints SET data = substr(data, 1, length(data) - 6) WHERE image_id = 2")


def _nan_keypoints(db: Path) -> None:
    con = sqlite3.connect(db)
    r, c, d = con.execute("SELECT rows, cols, data FROM keypoints WHERE image_id = 2").fetchone()
    a = np.frombuffer(d, np.float32).copy().reshape(r, c)
    a[3, 0] = np.nan
    a[5, 1] = np.inf
    con.execute("UPDATE keypoints SET data = ? WHERE image_id = 2", (a.tobytes(),))
    con.commit()
    con.close()


def _text_file(db: Path) -> None:
    db.write_text("image_id,name\n1,a.jpg\n")


def _h5_case(mutate):
    def build(folder: Path, env: dict):
        import h5py

        f = folder / "features.h5"
        shutil.copy(env["features"], f)
        with h5py.File(f, "a") as fh:
            mutate(fh, sorted(fh.keys())[1])
        return ["hloc", f, "exhaustive", folder / "matches.h5", "--workers", "0", "--no-progress", "--log",
                "none"], f
    return build


def _h5_del(ds: str):
    def go(fh, g):
        del fh[g][ds]
    return go


def _h5_dtype(ds: str, dtype):
    def go(fh, g):
        data = np.asarray(fh[g][ds])
        del fh[g][ds]
        if dtype == "str":
            fh[g].create_dataset(ds, data=np.array([b"x" * 8] * data.shape[-1]).reshape(1, -1).repeat(data.shape[0], 0)
                                 if data.ndim == 2 else np.array([b"x"] * len(data)))
        else:
            fh[g].create_dataset(ds, data=data.astype(dtype))
    return go


def _h5_nan(fh, g):
    kp = np.asarray(fh[g]["keypoints"]).copy()
    kp[2, 0] = np.nan
    fh[g]["keypoints"][...] = kp


def _h5_truncated(folder: Path, env: dict):
    f = folder / "features.h5"
    data = Path(env["features"]).read_bytes()
    f.write_bytes(data[:len(data) // 2])
    return ["hloc", f, "exhaustive", folder / "matches.h5", "--workers", "0", "--no-progress", "--log", "none"], f


def _pairs_case(lines):
    def build(folder: Path, env: dict):
        db = _copy_db(env, folder)
        p = folder / "pairs.txt"
        names = env["names"]
        text = lines(names)
        p.write_bytes(text if isinstance(text, bytes) else text.encode())
        return ["colmap", db, "--pairs", p, "--workers", "0", "--no-progress", "--log", "none"], p
    return build


# -- images: guidedmatch sfm on a folder of good views plus one bad file; guidedmatch match on the bad file
def _img_bytes(kind: str, good: Path) -> tuple[str, bytes]:
    """(file name, content) of a bad / unusual image made from the good image ``good``."""
    import cv2
    from PIL import Image

    buf = io.BytesIO()
    if kind == "zero":
        return "empty.jpg", b""
    if kind == "text":
        return "notes.jpg", b"this is not an image\n" * 20
    if kind == "truncated":
        img = cv2.imread(str(good))
        ok, enc = cv2.imencode(".jpg", img)
        return "cut.jpg", enc.tobytes()[: len(enc) // 2]
    if kind == "1x1":
        Image.new("L", (1, 1), 128).save(buf, "PNG")
        return "dot.png", buf.getvalue()
    if kind == "16bit":
        g = cv2.imread(str(good), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 257
        ok, enc = cv2.imencode(".png", g)
        return "deep16.png", enc.tobytes()
    if kind == "cmyk":
        Image.open(good).convert("RGB").convert("CMYK").save(buf, "JPEG", quality=95)
        return "cmyk.jpg", buf.getvalue()
    if kind == "exif":
        im = Image.open(good).convert("RGB").transpose(Image.Transpose.ROTATE_90)  # stored sideways ...
        exif = Image.Exif()
        exif[0x0112] = 6                                                            # ... and tagged: rotate back
        im.save(buf, "JPEG", quality=95, exif=exif.tobytes())
        return "rotated.jpg", buf.getvalue()
    raise ValueError(kind)


def _images_case(kind: str, command: str):
    def build(folder: Path, env: dict):
        images = folder / "images"
        images.mkdir()
        goods = sorted(Path(env["images"]).iterdir())[: env.get("n_good", 3)]
        for g in goods:
            shutil.copy(g, images / g.name)
        if kind == "unicode":
            src = images / goods[0].name
            bad = images / "vue d'été – 01 ✓.png"
            src.rename(bad)
        elif kind == "non-image files":
            (images / "README.txt").write_text("shot on a tripod\n")
            (images / ".DS_Store").write_bytes(b"\0\1\2")
            (images / "notes.md").write_text("# notes\n")
            bad = images / "README.txt"
        else:
            name, data = _img_bytes(kind, goods[0])
            bad = images / name
            bad.write_bytes(data)
        if command == "sfm":
            return ["sfm", images, folder / "project", "--workers", "0", "--max-features", "1000", "--threads",
                    "2"], bad
        return ["match", bad, images / goods[1].name], bad
    return build


def input_cases() -> list[Case]:
    cases = [
        Case("database", "truncated database (half its bytes)", _db_case(_truncate(0.5))),
        Case("database", "database cut to 100 bytes", _db_case(_truncate(100 / 2e6))),
        Case("database", "0-byte database", _db_case(_truncate(0.0))),
        Case("database", "a text file named .db", _db_case(_text_file)),
        Case("database", "wrong schema: an SQLite file of another program", _db_case(_wrong_schema)),
        Case("database", "wrong schema: keypoints table with other columns", _db_case(_broken_table)),
        Case("database", "descriptor blob of the wrong size", _db_case(_short_descriptor_blob)),
        Case("database", "keypoint blob of the wrong size", _db_case(_short_keypoint_blob)),
        Case("database", "keypoints with NaN / inf", _db_case(_nan_keypoints)),
        Case("h5", "h5: an image without descriptors", _h5_case(_h5_del("descriptors"))),
        Case("h5", "h5: an image without keypoints", _h5_case(_h5_del("keypoints"))),
        Case("h5", "h5: an image without image_size", _h5_case(_h5_del("image_size"))),
        Case("h5", "h5: descriptors of dtype int64", _h5_case(_h5_dtype("descriptors", np.int64))),
        Case("h5", "h5: descriptors stored as strings", _h5_case(_h5_dtype("descriptors", "str"))),
        Case("h5", "h5: keypoints of dtype complex", _h5_case(_h5_dtype("keypoints", np.complex64))),
        Case("h5", "h5: keypoints with NaN", _h5_case(_h5_nan)),
        Case("h5", "truncated features.h5", _h5_truncated),
        Case("pairs", "pairs file naming an unknown image",
             _pairs_case(lambda n: f"{n[0]} {n[1]}\n{n[0]} ghost.png\n")),
        Case("pairs", "pairs file with the same pair twice (and reversed)",
             _pairs_case(lambda n: f"{n[0]} {n[1]}\n{n[0]} {n[1]}\n{n[1]} {n[0]}\n{n[1]} {n[2]}\n"),
             accept=r"duplicate|repeated|dropped"),
        Case("pairs", "pairs file with a self-pair", _pairs_case(lambda n: f"{n[0]} {n[0]}\n{n[0]} {n[1]}\n"),
             accept=r"self"),
        Case("pairs", "pairs file with a one-name line", _pairs_case(lambda n: f"{n[0]} {n[1]}\n{n[2]}\n")),
        Case("pairs", "empty pairs file", _pairs_case(lambda n: "")),
        Case("pairs", "binary pairs file", _pairs_case(lambda n: b"\xff\xfe\x00\x01" * 50)),
    ]
    for command in ("match", "sfm"):
        skip = None if command == "match" else SKIPPED   # sfm documents: a damaged image is skipped and listed
        for kind, accept in (("zero", skip), ("text", skip), ("truncated", skip), ("1x1", skip),
                             ("16bit", r"" if command == "match" else r"registered"),
                             ("cmyk", r"" if command == "match" else r"registered"),
                             ("exif", r"" if command == "match" else r"registered"),
                             ("unicode", r"" if command == "match" else r"registered"),
                             ("non-image files", None if command == "match" else r"registered")):
            if command == "match" and kind == "non-image files":
                accept = None
            label = {"zero": "0-byte image", "text": "a text file named .jpg", "truncated": "truncated JPEG",
                     "1x1": "1x1 image", "16bit": "16-bit PNG", "cmyk": "CMYK JPEG", "exif": "EXIF-rotated JPEG",
                     "unicode": "unicode and spaces in the name", "non-image files": "non-image files"}[kind]
            cases.append(Case(f"images ({command})", f"{command}: {label}", _images_case(kind, command), accept))
    return cases


#: ``Case.accept`` of a damaged image given to sfm: exit 0 is right when the image is skipped and listed by name
#: in the project's report.json (``skipped_images``) -- and it must not be among the registered images
SKIPPED = "<skipped and listed>"


def _skipped_and_listed(argv, named: Path) -> bool:
    import json

    try:
        report = json.loads((Path(argv[2]) / "report.json").read_text())
    except (OSError, ValueError, IndexError):
        return False
    return any(Path(str(s.get("name", ""))).name == named.name for s in report.get("skipped_images", []))


def check_case(case: Case, run: Run, named: Path) -> list[str]:
    """What is wrong with the outcome of one case (empty: as expected)."""
    import re

    problems = []
    if run.bug:
        problems.append("traceback / internal error")
    if run.rc == 2:
        msg = run.stderr
        if str(named) not in msg and named.name not in msg:
            problems.append(f"the message does not name {named.name}")
    elif run.rc == 0 and case.accept == SKIPPED:
        if not _skipped_and_listed(run.argv, named):
            problems.append(f"exit 0 and {named.name} is not in report.json's skipped_images (used?)")
    elif run.rc == 0 and case.accept is not None:
        if case.accept and not re.search(case.accept, run.stdout + run.stderr, re.I):
            problems.append(f"exit 0 without saying how it was handled (/{case.accept}/)")
    else:
        problems.append(f"exit {run.rc}" + (" (accepted silently)" if run.rc == 0 else ""))
    return problems


def run_cases(cases, scratch: Path, env: dict, runner=run_cli) -> list[dict]:
    out = []
    for i, case in enumerate(cases):
        folder = scratch / f"case{i:02d}"
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        argv, named = case.build(folder, env)
        run = runner(argv)
        problems = check_case(case, run, named)
        out.append(dict(group=case.group, case=case.name, ok=not problems, rc=run.rc, problems=problems,
                        bug=run.bug, message=run.tail(240), argv=[str(a) for a in argv]))
    return out


def corrupt_inputs(scratch: Path, coll: dict | None = None) -> list[Row]:
    """Every case of :func:`input_cases`, each in a fresh process; one table row per group."""
    from .faults_common import make_collection

    scratch.mkdir(parents=True, exist_ok=True)
    small = make_collection(scratch / "collection", n_images=4, size=(480, 360), max_features=800, seed=7)
    env = dict(db=small["db"], names=small["names"], images=small["images"],
               features=make_features_h5(small["db"], scratch / "features.h5"))
    results = run_cases(input_cases(), scratch / "cases", env)
    rows = {}
    for r in results:
        row = rows.setdefault(r["group"], Row(f"corrupt inputs: {r['group']}"))
        row.add(r["ok"], bug=r["bug"], case=r["case"], rc=r["rc"], message=r["message"], problems=r["problems"])
        print(f"  {r['case']}: exit {r['rc']}{'' if r['ok'] else ' FAILED: ' + '; '.join(r['problems'])}",
              flush=True)
    return list(rows.values())


# ============================================================================================ fuzzing
JUNK = ("", "-", "--", "x", "0", "-1", "1e9", "nan", "inf", "-inf", "1.5", "99999999999999999999", "a=b", "=",
        "ratio=2", "ratio=nan", "band_px=-3", "threads=0", "none", "true", "ü ñ 字", "--debug", "-h", "%s%n",
        "sequential:0", "sequential:-2", "sequential:x", "exhaustive", "100x100", "0x0", "64x64", "PINHOLE:1,2",
        "PINHOLE:1,2,3,4", "ours:orb", "ours:nope", "tcp://127.0.0.1:1", "colmap", "sift", "so+epi+ia", "bf")


def fuzz_env(folder: Path) -> dict:
    """Paths the fuzzer draws from: missing, a folder, a text file, an image, a tiny database / features.h5 /
    pairs file, unwritable places."""
    from .faults_common import make_collection

    folder.mkdir(parents=True, exist_ok=True)
    small = make_collection(folder / "collection", n_images=3, size=(320, 240), max_features=300, seed=3)
    feats = make_features_h5(small["db"], folder / "features.h5")
    (folder / "notes.txt").write_text("hello\n")
    (folder / "pairs.txt").write_text(f"{small['names'][0]} {small['names'][1]}\n")
    img = sorted(small["images"].iterdir())[0]
    return {"paths": [str(p) for p in (folder / "missing.db", folder, folder / "notes.txt", img, small["db"], feats,
                                       folder / "pairs.txt", small["images"], folder / "out" / "m.npz",
                                       "/proc/nope/out", "/etc/hostname/out", folder / "out.h5")],
            "db": small["db"]}


def _option_values(action, paths) -> list:
    vals = list(JUNK) + list(paths)
    if action.choices:
        vals = list(action.choices) * 3 + vals
    return vals


def fuzz_arguments(scratch: Path, examples: int, seed: int = 0) -> Row:
    """``examples`` hypothesis-drawn argument lists per subcommand, each run in this process (stdout / stderr
    captured): exit 0 or 2, never a traceback. Heavy work a valid list would start is bounded: bench runners are
    replaced by a stub after their arguments are checked, demo / experiment get a small size first, and any run
    is stopped after 30 s (counted as ran, not as a failure)."""
    import os

    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    import importlib

    build_parser = importlib.import_module("guidedmatch.cli").build_parser  # the CLI under test, at call time

    scratch.mkdir(parents=True, exist_ok=True)
    env = fuzz_env(scratch)
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    row = Row("fuzzed arguments (every subcommand)")
    cwd = os.getcwd()
    stubs = _stub_benches()
    try:
        os.chdir(scratch)
        for cmd, sp in sorted(sub.choices.items()):
            opts = [a for a in sp._actions if a.option_strings and a.dest != "help"]
            token = st.one_of(
                st.sampled_from(JUNK + tuple(env["paths"])),
                st.sampled_from(opts).flatmap(lambda a: st.tuples(
                    st.sampled_from(a.option_strings),
                    st.sampled_from(_option_values(a, env["paths"])) if a.nargs != 0 else st.just(None))),
                st.text(min_size=0, max_size=12).filter(lambda s: "\0" not in s))
            prefix = {"demo": ["--size", "96x96"], "experiment": ["alignment", "--pairs", "5"]}.get(cmd, [])
            seen = []

            @settings(max_examples=max(1, examples // (4 if cmd in ("demo", "experiment", "sfm") else 1)),
                      deadline=None, database=None, derandomize=True, suppress_health_check=list(HealthCheck))
            @given(st.lists(token, min_size=0, max_size=7))
            def one(tokens):
                argv = [cmd] + list(prefix)
                for t in tokens:
                    if isinstance(t, tuple):
                        argv += [t[0]] + ([] if t[1] is None else [str(t[1])])
                    else:
                        argv.append(str(t))
                run = run_inprocess(argv, timeout=30)
                timeout = run.rc is None and run.stderr.endswith("[timeout]")
                ok = timeout or (run.rc in (0, 2) and not run.bug)
                bug = run.bug or (run.rc is None and not timeout)
                seen.append(dict(ok=ok, bug=bug, argv=argv, rc=run.rc, timeout=timeout,
                                 tail="" if ok else (run.stderr.strip().splitlines() or [""])[-1][-300:]))
            one()
            bad = [s for s in seen if not s["ok"]]
            row.trials += len(seen)
            row.survived += len(seen) - len(bad)
            row.tracebacks += sum(s["bug"] for s in bad)
            n_to = sum(s["timeout"] for s in seen)
            row.details.append(dict(command=cmd, examples=len(seen), failed=len(bad), timeouts=n_to,
                                    exit_codes=sorted({str(s["rc"]) for s in seen}), failures=bad[:10]))
            print(f"  fuzz {cmd}: {len(seen)} argument lists, {len(bad)} failed, {n_to} stopped after 30 s",
                  flush=True)
            for b in bad[:3]:
                row.notes.append(f"`guidedmatch {' '.join(b['argv'])}` -> exit {b['rc']}: {b['tail']}")
    finally:
        os.chdir(cwd)
        for mod, name, old in stubs:
            setattr(mod, name, old)
    row.notes.insert(0, f"{row.trials} argument lists in all (survived: exit 0 or 2 without a traceback; an exit 1 "
                        "without a traceback fails it but is not counted as one); the bench runners of "
                        "`guidedmatch bench` replaced by a stub after their argument checks")
    return row


def _stub_benches() -> list:
    """Replace the runners ``guidedmatch bench`` calls after its checks by a stub (restored by the caller)."""
    import importlib

    replaced = []
    for modname, fn in (("guidedmatch.evaluation.bench", "run_benchmarks"),
                        ("guidedmatch.evaluation.bench_sfm", "main"), ("guidedmatch.evaluation.bench_pairs", "main"),
                        ("guidedmatch.evaluation.bench_collection", "main"),
                        ("guidedmatch.evaluation.bench_faults", "main")):
        try:
            mod = importlib.import_module(modname)
        except Exception:  # noqa: BLE001
            continue
        if hasattr(mod, fn):
            replaced.append((mod, fn, getattr(mod, fn)))
            setattr(mod, fn, lambda *a, **k: 0)
    return replaced
