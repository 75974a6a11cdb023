"""The large-collection benchmark's bookkeeping (guidedmatch.evaluation.bench_large): names, scenes, database pairs."""
from __future__ import annotations

import shutil

from guidedmatch.datasets import data_root
from guidedmatch.evaluation.bench_large import FOLDERS, db_pairs, image_names, markdown, scene_of
from guidedmatch.testing.data import needs_data


@needs_data("collections/scenes.txt", *(f"{f}/*" for f in FOLDERS))
def test_names_are_unique_relative_paths_and_scenes_follow_the_labels():
    root = data_root()
    names = image_names(root)
    assert len(names) == len(set(names)) == 220
    scenes = scene_of(root, names)
    p8 = [n for n in names if "Herz-Jesus-P8" in n]
    assert len(p8) == 8 and {scenes[n] for n in p8} == {"Herz-Jesus-P25"}
    photos = [n for n in names if n.startswith("photos/")]
    assert len({scenes[n] for n in photos}) == len(photos) == 24  # each photo its own scene
    n = len(names)
    same = sum(scenes[names[i]] == scenes[names[j]] for i in range(n) for j in range(i + 1, n))
    assert same == 5356  # C(33,2) + 2 C(67,2) + C(29,2), as the collection's README counts


def test_db_pairs_reads_tried_and_verified_pairs_with_sorted_names(tmp_path):
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import images_to_database
    from guidedmatch.testing.multiview import make_multiview, write_views

    mv = make_multiview(3, (320, 240), seed=1, isolated=False, spacing=0.5)
    write_views(mv, tmp_path / "img")
    src = images_to_database(tmp_path / "img", tmp_path / "db.db", progress=False)
    from guidedmatch.collection.engine import match_collection

    with ColmapSink(tmp_path / "db.db") as sink:
        rep = match_collection(src, [("view_01.png", "view_00.png"), ("view_01.png", "view_02.png")], sink,
                               dict(progress=False, workers=0))
    d = db_pairs(tmp_path / "db.db")
    assert d["tried"] == {("view_00.png", "view_01.png"), ("view_01.png", "view_02.png")}
    assert set(d["verified"]) <= d["tried"]
    assert sum(d["verified"].values()) == rep.totals["inliers"]


def test_markdown_table_has_one_row_per_method():
    row = dict(wall_s=10.0, pairs_tried=5, pairs_verified=3, recall=0.5, reference_tried=2, verified_across_scene=0,
               inner={})
    res = dict(images=4, pairs=6, across_pairs=2, k=2, load_start=[1, 1, 1], extraction=dict(extract_s=1.0),
               reference=dict(reference=4, min_inliers=100, reference_strong=5, reference_dropped_across=1),
               rows={"colmap_exhaustive": dict(row), "ours_retrieval": dict(row, wall_s=1.0,
                                                                             retrieval=dict(retrieval_s=0.1,
                                                                                            share=0.1))})
    md = markdown(res)
    assert "| colmap_exhaustive | 10 | 1.000 |" in md and "| ours_retrieval | 1 | 0.100 |" in md
    assert "retrieval stage 0.1 s = 10.0 %" in md


def test_models_are_judged_by_scene_and_a_mixed_model_is_named(tmp_path):
    """judge_models: registered per scene = the scene's images in its largest model; any model holding two scene
    labels is reported as mixing them; scenes without reference poses get none."""
    from guidedmatch.evaluation.large_models import judge_models, models_markdown

    scenes = {f"lund/{i}.jpg": "lund" for i in range(5)}
    scenes.update({"photos/a.jpg": "photos/a.jpg", "photos/b.jpg": "photos/b.jpg"})
    models = [[f"lund/{i}.jpg" for i in range(3)], ["lund/3.jpg", "lund/4.jpg", "photos/a.jpg"]]
    j = judge_models(models, tmp_path, scenes, tmp_path)
    assert j["models"] == 2 and j["registered"]["lund"] == 3 and j["registered"]["photos/b.jpg"] == 0
    assert j["mixed"] == [{"model": 1, "scenes": {"lund": 2, "photos/a.jpg": 1}}]
    assert j["scene_images"]["lund"] == 5 and j["poses"]["buddha"]["registered"] == 0
    md = models_markdown({"maps": {"ours": {"wall_s": 1.0, "judged": j}}, "pipelines": {}})
    assert "| ours | 1 | 2 | 1 |" in md


def test_image_links_keep_the_names_and_read_the_data_in_place(tmp_path):
    from guidedmatch.collection.image_folder import list_images
    from guidedmatch.evaluation.large_models import image_links

    data = tmp_path / "data"
    (data / "a" / "images").mkdir(parents=True)
    (data / "b").mkdir()
    for n in ("a/images/1.jpg", "b/2.png"):
        (data / n).write_bytes(b"x")
    out = image_links(data, ["a/images/1.jpg", "b/2.png"], tmp_path / "links")
    assert list_images(out) == ["a/images/1.jpg", "b/2.png"]
    assert (out / "b/2.png").is_symlink() and (out / "b/2.png").resolve() == (data / "b/2.png").resolve()
    image_links(data, ["a/images/1.jpg"], out)   # again: nothing to do, no error


def test_bench_sfm_set_large_runs_bench_large_with_the_pipelines_and_sfm(tmp_path, monkeypatch):
    """`guidedmatch bench sfm --set large` = bench large's photos -> model rows (COLMAP exhaustive and vocabulary
    tree, mapped, and guidedmatch sfm), in OUT/large, data and work folders passed on."""
    from guidedmatch.cli import main as cli_main
    from guidedmatch.evaluation import bench_large

    seen = []
    monkeypatch.setattr(bench_large, "main", lambda argv=None: seen.append(argv) or 0)
    assert cli_main(["bench", "sfm", "--set", "large", "--data", str(tmp_path), "--work", str(tmp_path / "w"),
                     "--out", str(tmp_path / "out")]) == 0
    argv = seen[0]
    assert argv[argv.index("--out") + 1] == str(tmp_path / "out" / "large") and "--sfm" in argv
    assert argv[argv.index("--data") + 1] == str(tmp_path) and argv[argv.index("--work") + 1] == str(tmp_path / "w")
    assert set(argv[argv.index("--map") + 1].split(",")) == {"colmap_exhaustive", "colmap_vocabtree"}
    assert set(argv[argv.index("--sfm-mappers") + 1].split(",")) == {"incremental", "global"}
    assert {"colmap_exhaustive", "colmap_vocabtree", "ours_retrieval_expand"} <= set(argv[argv.index("--methods") + 1].split(","))


def test_bench_large_without_its_data_is_a_clear_error(tmp_path, capsys):
    import pytest

    from guidedmatch.evaluation.bench_large import main

    with pytest.raises(SystemExit) as e:
        main(["--data", str(tmp_path)])
    assert e.value.code == 2 and "no collections/ folder" in capsys.readouterr().err
