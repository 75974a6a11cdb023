import json

import cv2
import numpy as np
import pytest

from guidedmatch.cli import main, read_matches


@pytest.fixture(scope="module")
def image_files(tmp_path_factory, small_scene):
    d = tmp_path_factory.mktemp("imgs")
    cv2.imwrite(str(d / "a.png"), small_scene.image1)
    cv2.imwrite(str(d / "b.png"), small_scene.image2)
    cv2.imwrite(str(d / "blank.png"), np.full((100, 100), 127, np.uint8))
    (d / "corrupt.png").write_bytes(b"\x89PNG garbage")
    return d


def test_match_roundtrip_npz(image_files, tmp_path, capsys):
    out = tmp_path / "m.npz"
    rc = main(["match", str(image_files / "a.png"), str(image_files / "b.png"), "--mode", "bf", "-o", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "comparisons" in text and "matches" in text
    d = read_matches(out)
    assert d["pairs"].shape[1] == 2 and len(d["pairs"]) == len(d["distances"]) > 50
    np.testing.assert_array_equal(d["points1"], d["keypoints1"][d["pairs"][:, 0]])
    assert d["stats"]["comparisons"] == len(d["keypoints1"]) * len(d["keypoints2"])


@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_match_text_outputs(image_files, tmp_path, suffix):
    out = tmp_path / f"m{suffix}"
    assert main(["match", str(image_files / "a.png"), str(image_files / "b.png"), "--mode", "bf",
                 "--max-features", "300", "-o", str(out)]) == 0
    text = out.read_text()
    if suffix == ".json":
        assert len(json.loads(text)["pairs"]) > 0
    else:
        assert text.startswith("i1,i2,x1,y1,x2,y2,distance") and text.count("\n") > 10


@pytest.mark.parametrize("args,msg", [
    (["match", "{d}/missing.png", "{d}/b.png"], "not found"),
    (["match", "{d}/corrupt.png", "{d}/b.png"], "cannot read"),
    (["match", "{d}/blank.png", "{d}/b.png", "--mode", "bf"], "no features"),
    (["match", "{d}/a.png", "{d}/b.png", "--mode", "bf", "-o", "{d}/out.txt"], "unknown output format"),
    (["match", "{d}/a.png", "{d}/b.png", "--detector-option", "nonsense"], "key=value"),
])
def test_errors_are_one_line_without_traceback(image_files, capsys, args, msg):
    rc = main([a.format(d=image_files) for a in args])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("guidedmatch: error:") and msg in err
    assert "Traceback" not in err and err.count("\n") == 1
    assert not (image_files / "out.txt").exists()


def test_help_for_every_command(capsys):
    for cmd in (["--help"], ["match", "--help"], ["demo", "--help"], ["experiment", "--help"], ["bench", "--help"],
                ["colmap", "--help"], ["hloc", "--help"], ["extract", "--help"], ["map", "--help"], ["sfm", "--help"]):
        with pytest.raises(SystemExit) as e:
            main(cmd)
        assert e.value.code == 0
        assert "usage" in capsys.readouterr().out


def test_demo_small(tmp_path, capsys):
    rc = main(["demo", "--out", str(tmp_path), "--size", "480x360", "--roll", "20"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "precision" in out and "bf" in out
    assert (tmp_path / "demo_matches.png").stat().st_size > 10_000
    res = json.loads((tmp_path / "demo_results.json").read_text())
    assert res["rows"][0]["mode"] == "bf" and res["rows"][0]["true"] > 0


def test_guided_mode_with_config_plot_and_regions(image_files, tmp_path, capsys):
    a, b = str(image_files / "a.png"), str(image_files / "b.png")
    # small test images: auto_bf would replace guidance by brute force (below 2000 features)
    rc = main(["match", a, b, "--mode", "so+epi+ia", "--config", "update_every=60", "--config", "num_updates=2",
               "--config", "auto_bf=False", "--plot", str(tmp_path / "regions.png"), "--show-regions", "-o", str(tmp_path / "m.npz")])
    assert rc == 0, capsys.readouterr().err
    assert (tmp_path / "regions.png").stat().st_size > 10_000
    d = read_matches(tmp_path / "m.npz")
    assert d["stats"]["method"] == "so+epi+ia" and d["stats"]["num_model_updates"] == 2
    assert main(["match", a, b, "--mode", "epi", "--config", "update_every=60", "--config", "auto_bf=False",
                 "--plot", str(tmp_path / "mf.png")]) == 0
    assert (tmp_path / "mf.png").exists()


def test_bad_config_key_and_regions_without_model(image_files, tmp_path, capsys):
    a, b = str(image_files / "a.png"), str(image_files / "b.png")
    assert main(["match", a, b, "--config", "no_such_key=1"]) == 2
    err = capsys.readouterr().err
    assert "bad --config" in err and "band_px" in err and "no_such_key" in err and "Traceback" not in err
    assert main(["match", a, b, "--mode", "bf", "--plot", str(tmp_path / "r.png"), "--show-regions"]) == 2
    assert "needs a guided mode" in capsys.readouterr().err
    assert not (tmp_path / "r.png").exists()


def test_experiment_alignment_small(tmp_path, capsys):
    rc = main(["experiment", "alignment", "--pairs", "40", "--out", str(tmp_path)])
    assert rc == 0
    assert (tmp_path / "alignment_ratio.png").exists() and (tmp_path / "alignment_samples.csv").exists()
    assert "| " in capsys.readouterr().out  # the Markdown table is printed


@pytest.mark.parametrize("item", ["band_px=nan", "so_threshold=-1", "so_threshold=nan", "so_threshold=NaN",
                                  "ransac_threshold=-1", "seed=1.5", "max_distance=-1", "ransac_method=magsca",
                                  "band_px=Infinity", "so_probability=exact"])
def test_bad_config_exits_2_before_any_detection(item, capsys, monkeypatch, tmp_path):
    import guidedmatch.features as features

    def no_detection(*a, **k):
        raise AssertionError("detection ran before the config was checked")

    monkeypatch.setattr(features, "detect", no_detection)
    # the images do not even exist: the config error must come first
    rc = main(["match", str(tmp_path / "no1.png"), str(tmp_path / "no2.png"), "--config", item])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.startswith("guidedmatch: error: bad --config") and item.split("=")[0] in err
    assert "not found" not in err and "Traceback" not in err and err.count("\n") == 1


def test_other_exceptions_are_internal_errors_exit_1(image_files, capsys, monkeypatch):
    import guidedmatch.matcher as matcher

    def boom(*a, **k):
        raise RuntimeError("simulated bug")

    monkeypatch.setattr(matcher, "match", boom)
    args = ["match", str(image_files / "a.png"), str(image_files / "b.png"), "--max-features", "200"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert err.startswith("guidedmatch: internal error: RuntimeError: simulated bug") and "Traceback" not in err
    with pytest.raises(RuntimeError, match="simulated bug"):
        main(["--debug"] + args)


def test_unwritable_output_is_a_user_error_before_any_work(image_files, tmp_path, capsys, monkeypatch):
    import guidedmatch.features as features

    monkeypatch.setattr(features, "detect", lambda *a, **k: (_ for _ in ()).throw(AssertionError("detection ran")))
    blocker = tmp_path / "file"
    blocker.write_text("x")
    a, b = str(image_files / "a.png"), str(image_files / "b.png")
    for args in (["match", a, b, "-o", str(blocker / "m.npz")], ["match", a, b, "--plot", str(blocker / "p.png")],
                 ["demo", "--out", str(blocker / "demo")]):
        assert main(args) == 2, args
        err = capsys.readouterr().err
        assert err.startswith("guidedmatch: error: cannot ") and err.count("\n") == 1
        assert str(blocker) in err and ".tmp" not in err  # names the user's path, not an internal temp file


def test_debug_is_accepted_after_the_subcommand(image_files, capsys, monkeypatch):
    """--debug before or after the subcommand shows the traceback; without it, one line."""
    import guidedmatch.matcher as matcher

    def boom(*a, **k):
        raise RuntimeError("simulated bug")

    monkeypatch.setattr(matcher, "match", boom)
    args = ["match", str(image_files / "a.png"), str(image_files / "b.png"), "--max-features", "200"]
    with pytest.raises(RuntimeError, match="simulated bug"):
        main(args + ["--debug"])
    with pytest.raises(RuntimeError, match="simulated bug"):
        main(["--debug"] + args)
    assert main(args) == 1
    missing = ["sfm", str(image_files / "nope"), str(image_files / "out")]
    assert main(missing) == 2
    from guidedmatch.errors import InputError

    with pytest.raises(InputError, match="not found"):
        main(missing + ["--debug"])


@pytest.mark.parametrize("make", [
    lambda d, blocker: ["sfm", str(d), str(blocker / "out")],
    lambda d, blocker: ["sfm", str(d), "/proc/guidedmatch-out"],
    lambda d, blocker: ["sfm", str(d), "/sys/guidedmatch-out"],
    lambda d, blocker: ["extract", str(d), str(blocker / "db" / "database.db")],
    lambda d, blocker: ["extract", str(d), "/proc/database.db"],
    lambda d, blocker: ["map", str(blocker.parent / "x.db"), str(d), str(blocker / "sparse")],
    lambda d, blocker: ["demo", "--out", "/proc/guidedmatch-demo"],
    lambda d, blocker: ["bench", "oxford", "--out", str(blocker / "reports")],
    lambda d, blocker: ["experiment", "alignment", "--out", "/sys/guidedmatch-exp"],
])
def test_output_folder_that_cannot_be_created_is_exit_2_with_path_and_reason(image_files, tmp_path, capsys, make):
    import pycolmap

    blocker = tmp_path / "file"
    blocker.write_text("x")
    db = pycolmap.Database.open(str(tmp_path / "x.db"))   # a database with a geometry, for map
    db.write_two_view_geometry(1, 2, pycolmap.TwoViewGeometry())
    db.close()
    args = make(image_files, blocker)
    assert main(args) == 2, args
    err = capsys.readouterr().err
    assert err.startswith("guidedmatch: error: cannot ") and err.count("\n") == 1 and "Traceback" not in err, err
    target = next(a for a in args if str(blocker) in a or a.startswith(("/proc", "/sys")))
    assert target.split("/")[1] in err and ("not a folder" in err or "does not accept" in err), err


def test_a_refused_write_anywhere_is_exit_2_naming_the_path(capsys, monkeypatch):
    """The last line of defence: the system refusing a file operation mid-run (a folder that cannot be made, a full
    disk) is the user's environment, not a bug: exit 2 with the reason and the path."""
    import errno

    import guidedmatch.cli.bench as bench

    def refused(args):
        raise OSError(errno.ENOSPC, "No space left on device", "/data/out/report.json")

    monkeypatch.setattr(bench, "cmd_experiment", refused)
    assert main(["experiment", "alignment"]) == 2
    err = capsys.readouterr().err
    assert err == "guidedmatch: error: No space left on device: /data/out/report.json\n"


@pytest.mark.parametrize("out", ["/proc/m.h5", "/sys/m.h5", "{blocker}/m.h5"])
def test_hloc_matches_file_that_cannot_be_written_is_exit_2(tmp_path, capsys, out):
    from guidedmatch.collection.sources import write_features_h5
    from guidedmatch.features import Features

    rng = np.random.default_rng(0)
    write_features_h5(tmp_path / "f.h5", {n: Features(rng.uniform(0, 99, (50, 2)), rng.normal(size=(50, 128))
                                                      .astype(np.float32), (100, 100), "sift") for n in "ab"})
    (tmp_path / "file").write_text("x")
    out = out.format(blocker=tmp_path / "file")
    assert main(["hloc", str(tmp_path / "f.h5"), "exhaustive", out, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("guidedmatch: error:") and err.count("\n") == 1 and out.rsplit("/", 1)[0] in err, err


@pytest.mark.parametrize("argv", [["colmap", ""], ["hloc", "", "exhaustive", ""], ["hloc", "f.h5", "exhaustive", "."]])
def test_an_empty_output_or_features_path_is_exit_2_not_an_internal_error(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("guidedmatch: error: ") and "path is empty" in err and "internal error" not in err


def test_bench_with_options_of_its_own_hands_the_command_line_to_its_module(capsys):
    from guidedmatch.cli.bench import DELEGATED, delegated_bench

    import inspect

    for name, (module, _) in DELEGATED.items():
        args = delegated_bench(["bench", name, "--out", "somewhere", "--debug"])
        assert args.debug
        if "argv" not in inspect.signature(__import__(module, fromlist=["main"]).main).parameters:
            assert args.out == "somewhere" and args.func.__module__ == module
    assert delegated_bench(["bench", "oxford", "--quick"]) is None   # the shared bench options
    with pytest.raises(SystemExit) as exc:
        main(["bench", "faults", "--no-such-option"])
    assert exc.value.code == 2 and "unrecognized arguments" in capsys.readouterr().err
