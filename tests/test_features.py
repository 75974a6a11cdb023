import numpy as np
import pytest

from guidedmatch.features import Features, detect, load_image


def test_detect_all_methods_on_scene(small_scene):
    for method, binary in (("sift", False), ("orb", True), ("akaze", True), ("brisk", True)):
        f = detect(small_scene.image1, method, max_features=300)
        assert 0 < len(f) <= 300
        assert f.binary == binary
        assert f.keypoints.dtype == np.float64 and f.keypoints.shape == (len(f), 2)
        assert f.image_size == (640, 480)


def test_colour_input_is_converted(small_scene):
    import cv2

    bgr = cv2.cvtColor(small_scene.image1, cv2.COLOR_GRAY2BGR)
    a = detect(bgr, max_features=200)
    b = detect(small_scene.image1, max_features=200)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)


def test_save_load_roundtrip(tmp_path, small_scene_features):
    f, _ = small_scene_features
    f.save(tmp_path / "f.npz")
    g = Features.load(tmp_path / "f.npz")
    np.testing.assert_array_equal(f.keypoints, g.keypoints)
    np.testing.assert_array_equal(f.descriptors, g.descriptors)
    assert g.kind == "sift" and g.image_size == f.image_size
    np.testing.assert_array_equal(f.scales, g.scales)


def test_from_cv_roundtrip(small_scene_features):
    f, _ = small_scene_features
    g = Features.from_cv(f.to_cv_keypoints(), f.descriptors, f.image_size, "sift")
    np.testing.assert_allclose(f.keypoints, g.keypoints, atol=1e-4)


def test_user_arrays_and_validation():
    f = Features.from_arrays(np.zeros((3, 2)), np.zeros((3, 32), np.uint8), (10, 10))
    assert f.binary
    g = Features.from_arrays(np.zeros((3, 2)), np.zeros((3, 128), np.uint8), (10, 10), kind="sift")
    assert not g.binary and g.descriptors.dtype == np.float32  # COLMAP-style uint8 SIFT is L2
    assert len(Features.from_arrays(np.zeros((0, 2)), np.zeros((0, 128), np.float32), (5, 5))) == 0
    with pytest.raises(ValueError, match="non-finite"):
        Features.from_arrays([[np.nan, 1.0]], np.zeros((1, 4), np.float32), (10, 10))
    with pytest.raises(ValueError, match="descriptors"):
        Features.from_arrays(np.zeros((3, 2)), np.zeros((2, 4), np.float32), (10, 10))
    with pytest.raises(ValueError, match="image_size"):
        Features.from_arrays(np.zeros((1, 2)), np.zeros((1, 4), np.float32), (0, 10))
    with pytest.raises(ValueError, match="uint8"):
        Features.from_arrays(np.zeros((1, 2)), np.zeros((1, 4), np.float32), (5, 5), kind="orb")


def test_load_image_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_image(tmp_path / "missing.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="cannot read"):
        load_image(bad)
    with pytest.raises(ValueError, match="empty"):
        load_image(np.zeros((0, 10), np.uint8))
    with pytest.raises(ValueError, match="directory"):
        load_image(tmp_path)


def test_blank_image_gives_zero_features():
    f = detect(np.full((200, 200), 128, np.uint8))
    assert len(f) == 0 and f.descriptors.shape[0] == 0


def test_unknown_detector_and_bad_option(small_scene):
    with pytest.raises(ValueError, match="unknown detector"):
        detect(small_scene.image1, "surf")
    with pytest.raises(ValueError, match="invalid option"):
        detect(small_scene.image1, "sift", noSuchOption=3)


def test_load_image_decodes_grey_files_with_the_decoders_conversion(tmp_path):
    """A grey read of a colour file is cv2.imread(IMREAD_GRAYSCALE) (libpng's / libjpeg's own conversion, what the
    benchmarks' ground-truth images have always been read with), not cvtColor of the colour decode, which differs
    by one grey level in about half of the pixels of a random colour image; colour reads are IMREAD_COLOR."""
    import cv2

    rgb = np.random.default_rng(0).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    path = tmp_path / "c.png"
    cv2.imwrite(str(path), rgb)
    decoder = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(load_image(path), decoder)
    np.testing.assert_array_equal(load_image(path, grey=False), cv2.imread(str(path), cv2.IMREAD_COLOR))
    converted = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)
    assert (converted != decoder).any()  # the two conversions do differ: the test can tell them apart
    np.testing.assert_array_equal(load_image(cv2.imread(str(path), cv2.IMREAD_COLOR)), converted)  # arrays: cvtColor
