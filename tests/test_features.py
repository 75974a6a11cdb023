import numpy as np
import pytest

from guidedmatch.features import (DETECTOR_PARAMS, Features, atomic_savez, atomic_write_text, check_detector_options,
                                  check_output_path, detect, detector_options, estimate_detect_memory, load_image)


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
    from guidedmatch.errors import ImageReadError

    with pytest.raises(ImageReadError, match="not found"):
        load_image(tmp_path / "missing.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(ImageReadError, match="cannot read"):
        load_image(bad)
    with pytest.raises(ImageReadError, match="empty"):
        load_image(np.zeros((0, 10), np.uint8))
    with pytest.raises(ImageReadError, match="directory"):
        load_image(tmp_path)


def test_blank_image_gives_zero_features():
    f = detect(np.full((200, 200), 128, np.uint8))
    assert len(f) == 0 and f.descriptors.shape[0] == 0


def test_unknown_detector_and_bad_option(small_scene):
    with pytest.raises(ValueError, match="unknown detector"):
        detect(small_scene.image1, "surf")
    with pytest.raises(ValueError, match="unknown sift option 'noSuchOption'.*contrastThreshold \\(float\\)"):
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


# ------------------------------------------------------------------ strict image reading
def _encoded(ext, rng):
    import cv2

    img = (rng.integers(0, 255, (96, 128)) // 32 * 32).astype(np.uint8)
    ok, buf = cv2.imencode(ext, cv2.GaussianBlur(img, (5, 5), 1.5))
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("ext", [".jpg", ".png"])
@pytest.mark.parametrize("keep", [0.3, 0.9, -2])
def test_truncated_images_are_image_read_errors_naming_the_file(tmp_path, rng, ext, keep):
    from guidedmatch.errors import ImageReadError

    data = _encoded(ext, rng)
    n = len(data) + keep if keep < 0 else int(len(data) * keep)
    path = tmp_path / f"cut{ext}"
    path.write_bytes(data[:n])
    with pytest.raises(ImageReadError, match=r"truncated or corrupt: .*cut\%s" % ext):
        load_image(path)
    whole = tmp_path / f"whole{ext}"
    whole.write_bytes(data)
    assert load_image(whole).shape == (96, 128)


def test_corrupt_jpeg_data_is_an_error_not_a_partial_decode(tmp_path, rng, capfd):
    from guidedmatch.errors import ImageReadError

    data = bytearray(_encoded(".jpg", rng))
    # a marker inside the entropy-coded data: libjpeg warns "Corrupt JPEG data: premature end of data segment" and
    # fills the rest with grey. (Bytes changed to other valid-looking data cannot be detected: JPEG has no checksum.)
    data[len(data) // 2: len(data) // 2 + 2] = b"\xff\xd9"
    (tmp_path / "c.jpg").write_bytes(bytes(data))
    with pytest.raises(ImageReadError, match="c.jpg"):
        load_image(tmp_path / "c.jpg")
    assert "Corrupt JPEG" not in capfd.readouterr().err  # captured into the error, not printed


def test_missing_image_is_both_image_read_error_and_file_not_found(tmp_path):
    from guidedmatch.errors import ImageReadError

    with pytest.raises(ImageReadError) as e:
        load_image(tmp_path / "nope.jpg")
    assert isinstance(e.value, FileNotFoundError) and "nope.jpg" in str(e.value)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ImageReadError, match="empty"):
        load_image(tmp_path / "empty.png")


# ------------------------------------------------------------------ max_image_size, memory guard, options
def _disc_image(rng, w=1200, h=900, r=9):
    import cv2

    pts = []
    while len(pts) < 40:
        p = rng.uniform([60, 60], [w - 60, h - 60])
        if all(np.hypot(*(p - q)) > 70 for q in pts):
            pts.append(p)
    img = np.full((h, w), 235, np.uint8)
    for x, y in pts:
        cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), r * 16, 20, -1, cv2.LINE_AA, shift=4)
    return cv2.GaussianBlur(img, (0, 0), 1.0), np.array(pts)


def test_max_image_size_reports_keypoints_and_scales_in_original_pixels(rng):
    img, centres = _disc_image(rng)
    full = detect(img)
    half = detect(img, max_image_size=600)
    assert half.image_size == full.image_size == (1200, 900)
    for f in (full, half):  # every disc centre has a blob keypoint on it, in original pixels
        d = np.hypot(*(f.keypoints[None] - centres[:, None]).transpose(2, 0, 1))
        near = d.argmin(axis=1)
        assert np.median(d.min(axis=1)) < 1.0, np.median(d.min(axis=1))
    # the blob's scale is the same in original pixels whichever resolution it was detected at
    def blob_scale(f):
        d = np.hypot(*(f.keypoints[None] - centres[:, None]).transpose(2, 0, 1))
        return np.median(f.scales[d.argmin(axis=1)])
    assert abs(blob_scale(half) / blob_scale(full) - 1) < 0.25
    assert detect(img, max_image_size=5000).keypoints.shape == full.keypoints.shape  # no upscaling
    with pytest.raises(ValueError, match="max_image_size"):
        detect(img, max_image_size=0)


def test_memory_guard_refuses_with_a_size_that_fits(monkeypatch):
    import guidedmatch.features as F
    from guidedmatch.errors import MemoryLimitError

    monkeypatch.setattr(F, "available_memory", lambda: 400 << 20)
    img = np.zeros((1500, 2000), np.uint8)
    with pytest.raises(MemoryLimitError, match=r"max_image_size=(\d+)") as e:
        detect(img)
    size = int(__import__("re").search(r"max_image_size=(\d+)", str(e.value)).group(1))
    assert 64 <= size < 2000
    s = size / 2000
    assert F.estimate_detect_memory(round(2000 * s), round(1500 * s), "sift") <= 0.8 * (400 << 20)
    assert len(detect(img, max_image_size=size)) == 0  # the suggested size passes the guard
    monkeypatch.setattr(F, "available_memory", lambda: None)  # unknown: no guard
    detect(img[:100, :100])


def test_memory_estimate_matches_the_measured_sift_peaks():
    # peaks measured by benchmarks/detect_memory.py (VmHWM; OpenCV 5.0) and by hand (6000x4500: 6.3 GB)
    for (w, h), measured in (((1000, 750), 179e6), ((3200, 2400), 1806e6), ((6000, 4500), 6.3e9)):
        est = estimate_detect_memory(w, h, "sift")
        assert measured <= est <= 1.1 * measured + (64 << 20)


@pytest.mark.parametrize("method,opts,msg", [
    ("sift", {"contrastThreshold": "abc"}, "contrastThreshold must be a float; got 'abc'"),
    ("sift", {"nOctaveLayers": 2.5}, "nOctaveLayers must be an int"),
    ("sift", {"nfeatures": 10}, "max_features"),
    ("orb", {"contrastThreshold": 0.1}, "unknown orb option 'contrastThreshold'.*fastThreshold \\(int\\)"),
    ("brisk", {"thresh": True}, "thresh must be an int"),
])
def test_detector_options_checked_by_name_and_type_with_the_list(method, opts, msg):
    from guidedmatch.errors import ConfigError

    with pytest.raises(ConfigError, match=msg):
        check_detector_options(method, opts)


def test_detector_options_accepted_and_converted():
    assert check_detector_options("sift", {"contrastThreshold": 0, "sigma": 1.2}) == {"contrastThreshold": 0.0,
                                                                                      "sigma": 1.2}
    for m in ("sift", "orb", "akaze", "brisk"):
        assert set(detector_options(m)) <= set(DETECTOR_PARAMS[m]) and detector_options(m)


def test_check_output_path(tmp_path):
    from guidedmatch.errors import OutputError

    assert check_output_path(tmp_path / "new" / "deeper" / "m.npz") == tmp_path / "new" / "deeper" / "m.npz"
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="file is not a folder"):
        check_output_path(tmp_path / "file" / "m.npz", "-o")
    with pytest.raises(OutputError, match="is a folder"):
        check_output_path(tmp_path, "-o")
    with pytest.raises(OutputError, match=r"-o /proc/m\.csv"):
        check_output_path("/proc/m.csv", "-o")
    assert not list(tmp_path.glob(".guidedmatch-probe-*"))


def test_atomic_writers_name_the_users_path_not_the_temp_file(tmp_path):
    from guidedmatch.errors import OutputError

    (tmp_path / "file").write_text("x")
    for write in (lambda p: atomic_savez(p, a=np.zeros(2)), lambda p: atomic_write_text(p, "x")):
        with pytest.raises(OutputError) as e:
            write(tmp_path / "file" / "m.npz")
        assert "tmp" not in str(e.value).replace(str(tmp_path), "") and "m.npz" in str(e.value)


def test_strict_reads_from_many_threads_leave_stderr_intact(tmp_path, rng, capfd):
    import os
    from concurrent.futures import ThreadPoolExecutor

    from guidedmatch.errors import ImageReadError

    import cv2

    good, cut = tmp_path / "g.jpg", tmp_path / "c.jpg"
    img = cv2.resize(rng.integers(0, 255, (96, 128)).astype(np.uint8), (1600, 1200))  # decodes slowly enough to race
    data = cv2.imencode(".jpg", img)[1].tobytes()
    good.write_bytes(data)
    bad = bytearray(data)
    bad[len(bad) // 2: len(bad) // 2 + 2] = b"\xff\xd9"
    cut.write_bytes(bytes(bad))

    def read(k):
        try:
            return load_image(good if k % 2 else cut).shape
        except ImageReadError:
            return "error"

    with ThreadPoolExecutor(4) as ex:
        res = list(ex.map(read, range(40)))
    assert res.count("error") == 20 and res.count((1200, 1600)) == 20
    os.write(2, b"still-stderr\n")  # fd 2 points at the real stderr again
    assert "still-stderr" in capfd.readouterr().err
