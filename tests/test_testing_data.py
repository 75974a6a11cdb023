import pytest

from guidedmatch.testing.data import missing_data, needs_data


def test_missing_data_names_absent_files_and_globs(tmp_path):
    (tmp_path / "oxford" / "bikes").mkdir(parents=True)
    (tmp_path / "oxford" / "bikes" / "img1.png").write_bytes(b"x")
    assert missing_data("oxford/bikes/img1.png", root=tmp_path) == []
    assert missing_data("oxford/bikes/img2.png", "photos/*.jpg", root=tmp_path) == ["oxford/bikes/img2.png",
                                                                                   "photos/*.jpg"]
    assert missing_data("oxford/*/img1.png", root=tmp_path) == []
    assert missing_data("a", root=tmp_path / "nowhere") == [f"<data root {tmp_path / 'nowhere'}>"]


def test_needs_data_skips_with_the_missing_files_in_the_reason(tmp_path, monkeypatch):
    monkeypatch.setenv("GUIDEDMATCH_DATA", str(tmp_path))  # an empty folder: every data test must skip
    mark = needs_data("oxford/bikes/img1.png", "x/y", "z", "w")
    assert mark.args == (True,)
    assert "oxford/bikes/img1.png, x/y, z (+1 more)" in mark.kwargs["reason"]
    (tmp_path / "f").write_text("")
    assert needs_data("f").args == (False,)


def test_bare_needs_data_requires_the_three_data_folders(tmp_path, monkeypatch):
    monkeypatch.setenv("GUIDEDMATCH_DATA", str(tmp_path))

    def t():
        pass

    marks = needs_data(t).pytestmark
    assert marks[0].args == (True,) and "oxford/*" in marks[0].kwargs["reason"]
    for d in ("oxford", "pose_pairs", "photos"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "x").write_text("")

    def u():
        pass

    assert needs_data(u).pytestmark[0].args == (False,)
