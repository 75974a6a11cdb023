"""guidedmatch sfm: bad inputs refused before work (exit 2, one line); config checks; the figure; end to end on a
rendered multi-view collection with known poses (every view registered, poses near the rendered cameras), report
files, resume."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from guidedmatch.errors import ConfigError
from guidedmatch.sfm import SfmConfig, list_images, parse_camera

SRC = str(Path(__file__).resolve().parents[1] / "src")


def run_cli(*args, timeout=600):
    env = {"PYTHONPATH": SRC, "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "guidedmatch.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


def _noise_png(path: Path, seed: int, size=(160, 120)):
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.GaussianBlur(rng.integers(0, 255, (size[1], size[0]), np.uint8), (0, 0), 1.5))


def _one_error_line(proc):
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("guidedmatch: error:"), proc.stderr
    assert "Traceback" not in proc.stderr
    return lines[0]


def test_empty_folder(tmp_path):
    (tmp_path / "img").mkdir()
    (tmp_path / "img" / "notes.txt").write_text("not an image")
    line = _one_error_line(run_cli("sfm", tmp_path / "img", tmp_path / "out"))
    assert "no images" in line
    assert not (tmp_path / "out").exists()


def test_missing_folder(tmp_path):
    line = _one_error_line(run_cli("sfm", tmp_path / "nope", tmp_path / "out"))
    assert "not found" in line


def test_one_image(tmp_path):
    _noise_png(tmp_path / "img" / "a.png", 0)
    (tmp_path / "img" / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")   # unreadable: only 1 readable image
    line = _one_error_line(run_cli("sfm", tmp_path / "img", tmp_path / "out", "--quiet"))
    assert "at least 2 usable images" in line and "b.png" in line
    assert not (tmp_path / "out" / "sparse").exists()


def test_foreign_database_refused(tmp_path):
    import pycolmap

    for i in range(3):
        _noise_png(tmp_path / "img" / f"{i}.png", i)
    out = tmp_path / "out"
    out.mkdir()
    db = pycolmap.Database.open(str(out / "database.db"))
    cam = pycolmap.Camera.create_from_model_name(0, "SIMPLE_RADIAL", 100.0, 160, 120)
    cid = db.write_camera(cam)
    db.write_image(pycolmap.Image(name="elsewhere.jpg", camera_id=cid))
    db.close()
    before = (out / "database.db").read_bytes()
    line = _one_error_line(run_cli("sfm", tmp_path / "img", out))
    assert "another project" in line or "not made by" in line
    assert (out / "database.db").read_bytes() == before
    assert sorted(p.name for p in out.iterdir()) == ["database.db"]


def test_project_of_another_folder_refused(tmp_path):
    for d in ("a", "b"):
        for i in range(2):
            _noise_png(tmp_path / d / f"{i}.png", i)
    out = tmp_path / "out"
    out.mkdir()
    (out / "database.db").write_bytes(b"")
    (out / "sfm_project.json").write_text(json.dumps({"image_dir": str((tmp_path / "a").resolve())}))
    line = _one_error_line(run_cli("sfm", tmp_path / "b", out))
    assert "belongs to the images in" in line


@pytest.mark.parametrize("kw", [dict(detector="ours:surf"), dict(detector="SIFT"), dict(max_features=0),
                                dict(camera="PINHOLE:1,2,3"), dict(camera="FISHEYE:1,2,3,4"),
                                dict(camera="PINHOLE:-1,1,1,1"), dict(geometry="both"), dict(mode="fast"),
                                dict(num_threads=0), dict(peak_threshold=0.002, detector="ours:sift"),
                                dict(matcher={"no_such_field": 1}), dict(pairs=""),
                                dict(max_inliers_per_pair=-1), dict(max_inliers_per_pair=99), dict(inlier_px=-1),
                                dict(inlier_px=float("nan")), dict(inlier_px="1.5"), dict(refit_below_deg=-1),
                                dict(refit_below_deg=181), dict(refit_below_deg=float("nan"))])
def test_config_errors(kw):
    with pytest.raises(ConfigError):
        SfmConfig(**kw)


def test_bad_option_via_cli_is_one_line(tmp_path):
    for i in range(2):
        _noise_png(tmp_path / "img" / f"{i}.png", i)
    line = _one_error_line(run_cli("sfm", tmp_path / "img", tmp_path / "out", "--camera", "PINHOLE:1,2"))
    assert "PINHOLE takes 4" in line
    assert not (tmp_path / "out").exists()


def test_parse_camera_and_listing(tmp_path):
    assert parse_camera("simple_pinhole:500,320,240") == ("SIMPLE_PINHOLE", [500.0, 320.0, 240.0])
    _noise_png(tmp_path / "x" / "b.PNG", 1)
    _noise_png(tmp_path / "a.png", 2)
    (tmp_path / "K.txt").write_text("1 0 0")
    assert list_images(tmp_path) == ["a.png", "x/b.PNG"]


def test_plot_reconstruction(tmp_path):
    """The figure from a synthetic pycolmap model (two cameras, a few points)."""
    import pycolmap

    from guidedmatch.sfm import plot_reconstruction

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", 100.0, 200, 100)
    rec.add_camera_with_trivial_rig(cam)
    for i in range(2):
        img = pycolmap.Image(name=f"{i}.png", camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([-float(i), 0, 0])))
    for k in range(50):
        rec.add_point3D(np.array([k * 0.01, 0.1, 3.0]), pycolmap.Track())
    p = plot_reconstruction(tmp_path / "r.png", rec, title="t")
    assert p.stat().st_size > 5000


# --------------------------------------------------------------------------- end to end (rendered collection)
@pytest.fixture(scope="module")
def rendered(five_views, tmp_path_factory):
    """5 rendered views (640x480, known K / R / t; conftest's ``five_views``) plus one unreadable file among them."""
    scene, views = five_views
    folder = tmp_path_factory.mktemp("mv") / "images"
    shutil.copytree(views, folder)
    (folder / "zz_broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 64)
    return scene, folder


def _known_camera(scene):
    K = scene.K   # OpenCV pixel convention; COLMAP's principal point is + 0.5
    return f"PINHOLE:{K[0, 0]:.6g},{K[1, 1]:.6g},{K[0, 2] + 0.5:.6g},{K[1, 2] + 0.5:.6g}"


def test_sfm_end_to_end_and_resume(rendered, tmp_path):
    """Our detector + known intrinsics: every view registered, relative poses within the stated tolerance of the
    rendered cameras; the unreadable file skipped and reported; a rerun reuses features and pairs."""
    pytest.importorskip("guidedmatch.collection.engine")
    import pycolmap

    from guidedmatch.evaluation.poses import CameraPose, evaluate_poses

    scene, folder = rendered
    out = tmp_path / "proj"
    args = ("sfm", folder, out, "--detector", "ours:sift", "--camera", _known_camera(scene), "--threads", "2",
            "--workers", "0", "--quiet")
    proc = run_cli(*args)
    assert proc.returncode == 0, proc.stderr
    for f in ("database.db", "report.json", "report.md", "reconstruction.png", "sparse/0/cameras.bin",
              "sparse/0/images.bin", "sparse/0/points3D.bin"):
        assert (out / f).is_file(), f
    rep = json.loads((out / "report.json").read_text())
    assert [s["name"] for s in rep["skipped_images"]] == ["zz_broken.png"]
    assert rep["num_images"] == 5 and rep["registered"] == 5 and rep["unregistered"] == []
    assert rep["stages"]["extraction"]["extracted"] == 5
    assert rep["stages"]["matching"]["collection"]["done"] == 10
    assert rep["stages"]["mapping"]["models"][0]["mean_reprojection_error_px"] < 1.0
    cap = rep["stages"]["matching"]["inlier_cap"]
    assert cap["max_inliers"] == 1000 and cap["above"] == 100_000    # the defaults: a few thousand inliers stay whole
    assert cap["applied"] is False and cap["pairs_capped"] == 0 and cap["inliers_after"] == cap["inliers_before"]
    assert "the mapper gets all of them (the cap of 1000 per pair applies above 100,000" in (out / "report.md").read_text()
    assert "zz_broken.png" in (out / "report.md").read_text()

    gt = {n: CameraPose(R, t) for n, R, t in zip(scene.names, scene.R, scene.t)}
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    ev = evaluate_poses(rec, gt)
    assert ev.num_registered == 5
    # stated tolerance: median relative-pose error <= 0.5 deg, every pair <= 2 deg (640x480 renders, ~1k SIFT per
    # view). Measured: worst pair 0.12 deg with the matcher of 20:00 UTC; 0.5-1.3 deg after merging main at 20:38
    # (matcher changes on main; COLMAP's multi-threaded mapper also varies run to run) -- reported to the lead.
    worst = max(r["error_deg"] for r in ev.per_pair)
    assert ev.median_error_deg <= 0.5 and worst <= 2.0, ev.summary()

    # time and peak memory of every stage, in the report and the summary line
    for st in rep["stages"].values():
        assert st["time_s"] >= 0 and st["peak_rss_mb"]["self"] > 10
    assert rep["peak_rss_mb"] >= max(st["peak_rss_mb"]["self"] for st in rep["stages"].values())
    assert rep["mapper"] == "incremental" and "peak memory" in rep["summary"] and "5/5 images" in rep["summary"]
    assert rep["mapper_rule"] == "auto: 5 images <= 100: incremental"  # the default mapper="auto" on a small folder
    assert "peak memory" in (out / "report.md").read_text() and "(auto: 5 images" in (out / "report.md").read_text()

    # rerun: nothing extracted or matched again, the model of the unchanged database reused
    proc = run_cli(*args)
    assert proc.returncode == 0, proc.stderr
    rep2 = json.loads((out / "report.json").read_text())
    assert rep2["stages"]["extraction"]["extracted"] == 0 and rep2["stages"]["extraction"]["reused"] == 5
    assert rep2["stages"]["matching"]["collection"]["done"] == 0
    assert rep2["stages"]["matching"]["collection"]["skipped"] == 10
    assert rep2["registered"] == 5 and rep2["stages"]["mapping"]["reused"] is True
    assert rep2["stages"]["mapping"]["models"] == rep["stages"]["mapping"]["models"]

    # other matching settings on the same project: refused before any work, the database untouched
    from guidedmatch.sfm import database_pair_stats

    before = database_pair_stats(out / "database.db")   # (opening with pycolmap bumps SQLite's change counter)
    line = _one_error_line(run_cli(*args, "--mode", "epi"))
    assert "were matched with" in line
    line = _one_error_line(run_cli(*args, "--inlier-px", "3"))   # the mapper's inliers are part of the matching
    assert "were matched with" in line and "'inlier_px': 3.0" in line
    line = _one_error_line(run_cli(*args, "--cap-above", "0"))   # the cap's rule too: it decides the mapper's inliers
    assert "were matched with" in line and "'cap_above': 0" in line
    # a project recorded before --cap-above capped whatever the total: it reads as cap_above 0, and the new default
    # (100,000) is refused on it with the options to rerun with
    project = out / "sfm_project.json"
    rec = json.loads(project.read_text())
    del rec["matching"]["cap_above"]
    project.write_text(json.dumps(rec))
    line = _one_error_line(run_cli(*args))
    assert "were matched with" in line and "'cap_above': 100000" in line
    assert database_pair_stats(out / "database.db") == before
    assert run_cli(*args, "--cap-above", "0").returncode == 0


def test_sfm_colmap_verification_single_camera(rendered, tmp_path):
    """COLMAP's verification of our matches, intrinsics estimated (one shared camera): every view registered."""
    pytest.importorskip("guidedmatch.collection.engine")
    scene, folder = rendered
    out = tmp_path / "proj"
    proc = run_cli("sfm", folder, out, "--detector", "ours:sift", "--single-camera", "--geometry", "colmap",
                   "--threads", "2", "--workers", "0", "--quiet", "--max-inliers-per-pair", "200", "--cap-above", "0")
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["registered"] == 5
    assert rep["stages"]["matching"]["verified_pairs"] >= 8
    assert rep["stages"]["matching"]["verify_time_s"] > 0
    # the cap applies to COLMAP's verification too: no pair hands the mapper more than 200 inliers
    cap = rep["stages"]["matching"]["inlier_cap"]
    assert cap["max_inliers"] == 200 and cap["pairs_capped"] >= 1 and cap["inliers_after"] < cap["inliers_before"]
    assert max(p["inliers"] for p in rep["pairs"]) == 200
    assert rep["stages"]["matching"]["verified_inliers"] == cap["inliers_after"]
    assert "the mapper gets at most 200 per pair" in (out / "report.md").read_text()


def test_mapper_profile_tool_reads_colmaps_log(rendered, tmp_path):
    """tools/mapper_profile.py on a real database: the model it reports is the one the mapper built, and every bundle
    adjustment is parsed (the global one after the initial pair first)."""
    import importlib.util

    from guidedmatch.sfm import run_sfm

    scene, folder = rendered
    rep = run_sfm(folder, tmp_path / "proj", {"detector": "ours:sift", "camera": _known_camera(scene), "workers": 0,
                                               "num_threads": 2, "progress": False})
    spec = importlib.util.spec_from_file_location(
        "mapper_profile", Path(__file__).resolve().parents[1] / "tools" / "mapper_profile.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    out = tool.profile(tmp_path / "proj" / "database.db", folder)
    assert out["registered"] == rep["registered"] == 5
    assert out["points"] > 100 and out["observations"] >= 2 * out["points"]
    rows = out["adjustments"]
    assert len(rows) >= 5 and rows[0]["stage"] == "Global bundle adjustment"
    assert all(r["residuals"] > 0 and r["iterations"] >= 1 and r["time_s"] >= 0 for r in rows)
    assert {r["termination"] for r in rows} <= {"CONVERGENCE", "NO_CONVERGENCE", "USER_SUCCESS"}
    assert any(r["stage"].startswith("Registering image #") for r in rows)


# --------------------------------------------------------------------------- the staged pipeline, mappers, scenes
def _truncated_copy(folder: Path, dest: Path) -> Path:
    """``folder``'s views plus ``cut.jpg``: a JPEG cut to half its bytes (libjpeg decodes it partially, with only a
    warning on stderr)."""
    shutil.copytree(folder, dest)
    (dest / "zz_broken.png").unlink()
    img = cv2.imread(str(folder / "view_00.png"), cv2.IMREAD_GRAYSCALE)
    ok, buf = cv2.imencode(".jpg", img)
    (dest / "cut.jpg").write_bytes(buf.tobytes()[: len(buf) // 2])
    return dest


def test_staged_pipeline_is_sfm_and_features_are_colmaps(rendered, tmp_path):
    """extract -> colmap -> map with COLMAP's SIFT: the extracted features are byte for byte those of
    pycolmap.extract_features on the same files, pycolmap's mapper reads them (every view registered, poses within
    the stated tolerance), the truncated JPEG is skipped by name (or refused with exit 2), and guidedmatch sfm gives
    the same database features and pairs."""
    import pycolmap

    from guidedmatch.evaluation.poses import CameraPose, evaluate_poses
    from guidedmatch.sfm import database_pair_stats

    scene, folder = rendered
    images = _truncated_copy(folder, tmp_path / "images")
    db = tmp_path / "staged" / "database.db"
    refused = run_cli("extract", images, db, "--bad-images", "refuse", "--quiet", "--detector", "colmap")
    line = _one_error_line(refused)
    assert "cut.jpg" in line and "truncated or corrupt" in line
    assert not db.exists() or not pycolmap.Database.open(str(db)).num_images()
    assert not db.with_name(db.name + ".guidedmatch.json").exists()   # refused: nothing left behind

    proc = run_cli("extract", images, db, "--quiet", "--detector", "colmap")
    assert proc.returncode == 0, proc.stderr
    assert "skipped    : cut.jpg:" in proc.stdout and "truncated or corrupt" in proc.stdout
    assert "next       : guidedmatch colmap" in proc.stdout
    again = run_cli("extract", images, db, "--quiet", "--detector", "colmap")          # resumable: nothing left to extract
    assert again.returncode == 0 and "extracted  : 0 image(s), 5 already" in again.stdout, again.stdout

    # the same features as COLMAP's own extractor reading the files itself
    ref = tmp_path / "ref.db"
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 1
    pycolmap.extract_features(str(ref), str(images), image_names=list(scene.names), extraction_options=opts,
                              device=pycolmap.Device.cpu)
    a, b = pycolmap.Database.open(str(db)), pycolmap.Database.open(str(ref))
    try:
        ours = {im.name: im.image_id for im in a.read_all_images()}
        theirs = {im.name: im.image_id for im in b.read_all_images()}
        assert sorted(ours) == sorted(theirs) == sorted(scene.names)
        for n in scene.names:
            np.testing.assert_array_equal(a.read_keypoints(ours[n]), b.read_keypoints(theirs[n]))
            np.testing.assert_array_equal(a.read_descriptors(ours[n]).data, b.read_descriptors(theirs[n]).data)
        assert [(c.model, c.width, c.height, list(c.params)) for c in a.read_all_cameras()] == \
               [(c.model, c.width, c.height, list(c.params)) for c in b.read_all_cameras()]
    finally:
        a.close()
        b.close()

    proc = run_cli("colmap", db, "--max-inliers-per-pair", "1000", "--workers", "0", "--no-progress")
    assert proc.returncode == 0, proc.stderr
    assert "next       : guidedmatch map" in proc.stdout
    # the renders' known intrinsics, held fixed: self-calibrating one camera per image from 5 views leaves the focal
    # (and with it every relative rotation) loosely determined -- on these very features COLMAP's own matcher gave
    # view_00 f = 5074 px (true 576) and a 1.30 deg median, ours f = 543-556 px and 0.86-1.85 deg depending on the
    # matcher settings; with K known the tolerance below tests the matches, not the self-calibration
    staged_db = pycolmap.Database.open(str(db))
    try:
        for cam in staged_db.read_all_cameras():
            cam.model = pycolmap.CameraModelId.PINHOLE
            cam.params = [scene.K[0, 0], scene.K[1, 1], scene.K[0, 2] + 0.5, scene.K[1, 2] + 0.5]
            staged_db.update_camera(cam)
    finally:
        staged_db.close()
    proc = run_cli("map", db, images, tmp_path / "staged" / "sparse", "--threads", "1", "--quiet",
                   "--fixed-intrinsics")  # one mapper thread
    assert proc.returncode == 0, proc.stderr
    assert "5 images" in proc.stdout and "next       : colmap gui" in proc.stdout
    rec = pycolmap.Reconstruction(str(tmp_path / "staged" / "sparse" / "0"))
    gt = {n: CameraPose(R, t) for n, R, t in zip(scene.names, scene.R, scene.t)}
    ev = evaluate_poses(rec, gt)
    # stated tolerance (known intrinsics, COLMAP SIFT on 640x480 renders): median <= 1 deg, every pair <= 3 deg
    assert ev.num_registered == 5 and ev.median_error_deg <= 1.0, ev.summary()
    assert max(r["error_deg"] for r in ev.per_pair) <= 3.0, ev.summary()

    # guidedmatch sfm = the same three stages: the same features and the same verified pairs
    proc = run_cli("sfm", images, tmp_path / "sfm", "--workers", "0", "--threads", "2", "--quiet", "--detector", "colmap")
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((tmp_path / "sfm" / "report.json").read_text())
    assert [s["name"] for s in rep["skipped_images"]] == ["cut.jpg"]
    assert "truncated or corrupt" in rep["skipped_images"][0]["reason"] and rep["registered"] == 5
    assert "cut.jpg" in proc.stdout + proc.stderr
    staged = {(r["name1"], r["name2"], r["verified"]) for r in database_pair_stats(db)}
    assert {(r["name1"], r["name2"], r["verified"]) for r in database_pair_stats(tmp_path / "sfm" / "database.db")} \
        == staged


def test_sfm_global_mapper(rendered, tmp_path):
    """``--mapper global`` (pycolmap.global_mapping): every view registered, poses within the stated tolerance, the
    report names the mapper and its time."""
    import pycolmap

    from guidedmatch.evaluation.poses import CameraPose, evaluate_poses

    scene, folder = rendered
    out = tmp_path / "proj"
    proc = run_cli("sfm", folder, out, "--detector", "ours:sift", "--camera", _known_camera(scene), "--threads", "2",
                   "--workers", "0", "--mapper", "global", "--quiet")
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["mapper"] == "global" and rep["stages"]["mapping"]["mapper"] == "global"
    assert rep["stages"]["mapping"]["time_s"] > 0 and "global mapper" in rep["summary"]
    ev = evaluate_poses(pycolmap.Reconstruction(str(out / "sparse" / "0")),
                        {n: CameraPose(R, t) for n, R, t in zip(scene.names, scene.R, scene.t)})
    # stated tolerance for the global mapper (known intrinsics): median <= 1 deg, every pair <= 3 deg
    assert ev.num_registered == 5 and ev.median_error_deg <= 1.0, ev.summary()
    assert max(r["error_deg"] for r in ev.per_pair) <= 3.0, ev.summary()


def test_cli_cap_above_default_is_the_sfm_constant():
    """The CLI writes CAP_ABOVE_INLIERS out (it does not import guidedmatch.sfm): both commands' --cap-above default
    and the SfmConfig default are that constant."""
    from guidedmatch.cli import build_parser
    from guidedmatch.sfm.config import CAP_ABOVE_INLIERS, SfmConfig

    sub = next(a for a in build_parser()._actions if hasattr(a, "choices") and isinstance(a.choices, dict))
    for cmd in ("sfm", "colmap"):
        opt = next(a for a in sub.choices[cmd]._actions if "--cap-above" in a.option_strings)
        assert opt.default == CAP_ABOVE_INLIERS == SfmConfig().cap_above
    with pytest.raises(ConfigError):
        SfmConfig(cap_above=-1)


def test_cli_mapper_help_states_the_auto_threshold():
    """The CLI writes the auto rule's threshold out (it does not import guidedmatch.sfm to build its parser): the
    text must say AUTO_GLOBAL_ABOVE."""
    from guidedmatch.cli import build_parser
    from guidedmatch.sfm.config import AUTO_GLOBAL_ABOVE

    sub = next(a for a in build_parser()._actions if hasattr(a, "choices") and isinstance(a.choices, dict))
    for cmd in ("sfm", "map"):
        mapper = next(a for a in sub.choices[cmd]._actions if "--mapper" in a.option_strings)
        assert f"global above {AUTO_GLOBAL_ABOVE} images" in mapper.help
    assert f"incremental up to {AUTO_GLOBAL_ABOVE} images" in sub.choices["sfm"].description


def test_auto_mapper_switches_to_global_above_the_threshold(rendered, tmp_path, monkeypatch):
    """``mapper="auto"`` (the default) maps with the global mapper when the database holds more images than
    AUTO_GLOBAL_ABOVE (lowered here to 3 for the 5-view scene); the report says which mapper ran and why, and a
    rerun with the same settings reuses that model."""
    from guidedmatch.sfm import config as sfm_config
    from guidedmatch.sfm import run_sfm

    monkeypatch.setattr(sfm_config, "AUTO_GLOBAL_ABOVE", 3)
    scene, folder = rendered
    conf = {"detector": "ours:sift", "camera": _known_camera(scene), "workers": 0, "num_threads": 2,
            "progress": False}
    rep = run_sfm(folder, tmp_path / "proj", conf)
    assert rep["mapper"] == "global" and rep["mapper_rule"] == "auto: 5 images > 3: global"
    assert rep["registered"] == 5 and "global mapper" in rep["summary"]
    again = run_sfm(folder, tmp_path / "proj", conf)
    assert again["stages"]["mapping"]["reused"] and again["mapper"] == "global"


@pytest.mark.parametrize("pairs", ["auto", "retrieval:2"])
def test_two_unrelated_scenes_give_two_models(tmp_path, pairs):
    """Two rendered scenes in one folder: two models, each holding the views of one scene only; both reported --
    with every pair (auto: 8 images) and with retrieval pairs (2 per image) + the verified expansion."""
    mv = pytest.importorskip("guidedmatch.testing.multiview")
    for sub, seed in (("a", 3), ("b", 4)):
        mv.write_views(mv.make_multiview(n_views=4, size=(640, 480), seed=seed, isolated=False, spacing=1.6),
                       tmp_path / "images" / sub)
    proc = run_cli("sfm", tmp_path / "images", tmp_path / "out", "--detector", "ours:sift", "--workers", "0",
                   "--threads", "2", "--quiet", "--pairs", pairs)
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert len(rep["models"]) == 2, rep["summary"]
    folders = [{n.split("/")[0] for n in m["registered_names"]} for m in rep["models"]]
    assert sorted(map(sorted, folders)) == [["a"], ["b"]]
    assert [m["registered"] for m in rep["models"]] == [4, 4] and rep["unregistered"] == []
    assert "2 models: 4 + 4 of 8 images" in rep["summary"]
    assert (tmp_path / "out" / "sparse" / "1" / "images.bin").is_file()
    assert "sparse/1" in (tmp_path / "out" / "report.md").read_text()
    tried = rep["stages"]["matching"]["pairs"] if "stages" in rep else None
    if pairs != "auto" and tried is not None:   # the shortlist tries fewer than all 28 pairs
        assert tried < 28


def test_a_second_sfm_on_the_same_project_is_refused_before_any_write(rendered, tmp_path):
    """Two processes on one project: the second gets exit 2 naming the lock holder, and the first's database is
    untouched by it; the lock is re-entrant within the process that holds it (its own sink opens it again)."""
    from guidedmatch.collection.sinks import WriteLock
    from guidedmatch.errors import DatabaseBusyError

    scene, folder = rendered
    out = tmp_path / "proj"
    out.mkdir()
    holder = WriteLock(out / "database.db", reentrant=True).acquire()   # stands for a running sfm in this process
    try:
        with WriteLock(out / "database.db"):              # re-entrant here
            pass
        assert holder.held and WriteLock._HELD           # still held after the inner release
        with pytest.raises(DatabaseBusyError):            # a non-re-entrant holder is refused even in-process
            _twice(tmp_path / "other.db")
        code = ("import fcntl, sys; fd = open(sys.argv[1] + '.lock', 'a'); fcntl.flock(fd, fcntl.LOCK_EX); "
                "print('locked', flush=True); sys.stdin.read()")
    finally:
        holder.release()
    # another process holds it: sfm and extract refuse at once, exit 2, nothing written
    proc = subprocess.Popen([sys.executable, "-c", code, str(out / "database.db")], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        for argv in (("sfm", folder, out, "--quiet"), ("extract", folder, out / "database.db", "--quiet")):
            res = run_cli(*argv)
            assert res.returncode == 2 and "being written by another process" in res.stderr, res.stderr
        assert not (out / "database.db").exists()
    finally:
        proc.stdin.close()
        proc.wait(timeout=30)


def _twice(target):
    from guidedmatch.collection.sinks import WriteLock

    first = WriteLock(target).acquire()
    try:
        WriteLock(target).acquire()
    finally:
        first.release()
