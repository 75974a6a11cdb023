import numpy as np
import pytest

from guidedmatch.datasets import (EpipolarGT, HomographyGT, data_root, oxford_pairs, strecha_pairs,
                                  synthesize_pair, synthetic_pairs)

from guidedmatch.testing.data import OXFORD_FILES, PHOTO_FILES, STRECHA_FILES, needs_data

ROOT = data_root()


def test_data_root_override_and_env(tmp_path, monkeypatch):
    monkeypatch.setenv("GUIDEDMATCH_DATA", str(tmp_path))
    assert data_root() == tmp_path
    missing = tmp_path / "x"
    # an explicit override wins over the environment variable and is returned as is although it does not exist
    # (never silently replaced by a folder that happens to exist); using it fails loudly, naming the variable
    assert not missing.exists() and data_root(missing) == missing
    with pytest.raises(FileNotFoundError, match="GUIDEDMATCH_DATA"):
        oxford_pairs(tmp_path / "missing")


def test_homography_gt_threshold(rng):
    H = np.array([[0.9, 0.1, 20], [-0.1, 0.9, 5], [1e-5, 0, 1]])
    gt = HomographyGT(H, (640, 480), (640, 480))
    p1 = rng.uniform(50, 400, (200, 2))
    p2 = gt.project(p1)
    assert gt.correct(p1, p2).all()
    assert gt.correct(p1, p2 + [0, 2.9]).all()
    assert not gt.correct(p1, p2 + [0, 3.1]).any()
    assert not gt.correct([[-10.0, 5.0]], gt.project([[-10.0, 5.0]])).any()  # outside image 1


def test_epipolar_gt_from_pose_agrees_with_scene(small_scene, rng):
    gt = EpipolarGT.from_pose(small_scene.K1, small_scene.K2, small_scene.R, small_scene.t)
    h, w = small_scene.image1.shape
    p1 = rng.uniform([0, 0], [w - 1, h - 1], (500, 2))
    p2, vis = small_scene.project(p1)
    assert gt.error(p1[vis], p2[vis]).max() < 1e-6
    assert gt.correct(p1[vis], p2[vis]).all()
    # move each image-2 point 10 px off its epipolar line (along the line normal): no longer correct
    lines = np.c_[p1[vis], np.ones(vis.sum())] @ gt.F.T
    normal = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    assert not gt.correct(p1[vis], p2[vis] + 10 * normal).any()


@pytest.mark.parametrize("set_id", [1, 2, 3])
def test_synthetic_homography_maps_image1_pixels_onto_image2(set_id, small_scene):
    """Warp a rendered image and check GT on SIFT matches: most ratio-test matches must be within 3 px."""
    from guidedmatch.bruteforce import match_bruteforce
    from guidedmatch.features import detect

    img1 = small_scene.image1
    img2, H, info = synthesize_pair(np.dstack([img1] * 3), set_id, rng=set_id)
    gt = HomographyGT(H, info["size1"], info["size2"])
    f1, f2 = detect(img1), detect(img2)
    r = match_bruteforce(f1, f2)
    ok = gt.correct(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]])
    err = gt.error(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]])
    assert len(r) > 50 and ok.mean() > 0.8
    assert np.median(err[ok]) < 1.0  # sub-pixel: the homography is exact, not just roughly right


@pytest.mark.data
@needs_data(*OXFORD_FILES, *STRECHA_FILES)
def test_oxford_and_strecha_pairs_load_with_consistent_gt():
    from guidedmatch.bruteforce import match_bruteforce
    from guidedmatch.features import detect

    ox = oxford_pairs(ROOT)
    assert len(ox) == 12 and ox[0].name == "oxford/bikes/1-2"
    p = ox[0]
    i1, i2 = p.load()
    f1, f2 = detect(i1, max_features=2000), detect(i2, max_features=2000)
    r = match_bruteforce(f1, f2)
    assert p.gt.correct(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]]).mean() > 0.7
    st = strecha_pairs(ROOT, with_sizes=False)
    assert len(st) == 18
    F = st[0].gt.F
    assert abs(np.linalg.det(F)) < 1e-8 and np.isclose(np.linalg.norm(F), 1.0)


@pytest.mark.data
@needs_data(*PHOTO_FILES)
def test_synthetic_pairs_are_deterministic_and_lazy():
    a = next(iter(synthetic_pairs(ROOT, 2, n_pairs=1, seed=3, max_side=500)))
    b = next(iter(synthetic_pairs(ROOT, 2, n_pairs=1, seed=3, max_side=500)))
    np.testing.assert_array_equal(a.gt.H, b.gt.H)
    i1, i2 = a.load()
    j1, j2 = b.load()
    np.testing.assert_array_equal(i2, j2)
    assert max(i1.shape[:2]) <= 500


# ------------------------------------------------------------------------------------------------
# data root, errors
# ------------------------------------------------------------------------------------------------
def test_data_root_search_order(tmp_path, monkeypatch):
    import guidedmatch.datasets as D

    monkeypatch.delenv("GUIDEDMATCH_DATA", raising=False)
    assert D.data_root(tmp_path / "explicit") == tmp_path / "explicit"  # override wins, returned as is
    # cwd/../shared/data is found; with neither cwd nor repo root holding one -> None
    work = tmp_path / "a" / "repo"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    monkeypatch.setattr(D.root, "_repo_root", lambda: tmp_path / "elsewhere" / "repo")
    assert D.data_root() is None
    (tmp_path / "a" / "shared" / "data").mkdir(parents=True)
    assert D.data_root() == (tmp_path / "a" / "shared" / "data").resolve()
    monkeypatch.setenv("GUIDEDMATCH_DATA", str(tmp_path / "env"))
    assert D.data_root() == tmp_path / "env"


def test_missing_files_raise_file_not_found_with_path_and_hint(tmp_path):
    import guidedmatch.datasets as D

    (tmp_path / "oxford" / "bikes").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match=r"img1\.png.*GUIDEDMATCH_DATA"):
        D.oxford_pairs(tmp_path, sequences=("bikes",))
    with pytest.raises(FileNotFoundError, match=r"oxford.*wall.*GUIDEDMATCH_DATA"):
        D.oxford_pairs(tmp_path, sequences=("wall",))
    cv2 = pytest.importorskip("cv2")
    cv2.imwrite(str(tmp_path / "oxford" / "bikes" / "img1.png"), np.zeros((7, 9), np.uint8))
    with pytest.raises(FileNotFoundError, match=r"H1to2p"):
        D.oxford_pairs(tmp_path, sequences=("bikes",), targets=(2,))
    with pytest.raises(FileNotFoundError, match=r"strecha_pairs_with_gt\.txt.*GUIDEDMATCH_DATA"):
        D.strecha_pairs(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"photos.*unsplash"):
        D.synthetic_pairs(tmp_path, 1)  # raised at call time, not at the first next()
    with pytest.raises(ValueError):
        D.synthetic_pairs(tmp_path, 4)


# ------------------------------------------------------------------------------------------------
# ground truth objects
# ------------------------------------------------------------------------------------------------
def test_homography_gt_rescaled_and_degenerate_points(rng):
    H = np.array([[1.1, 0.05, 12.0], [-0.04, 0.95, -7.0], [2e-5, -1e-5, 1.0]])
    gt = HomographyGT(H, (800, 600), (820, 640))
    p1 = rng.uniform(0, 500, (50, 2))
    p2 = gt.project(p1)
    s1, s2 = 0.5, 0.25
    g2 = gt.rescaled(s1, s2)
    q1, q2 = s1 * (p1 + 0.5) - 0.5, s2 * (p2 + 0.5) - 0.5  # pixel-centre convention
    np.testing.assert_allclose(g2.project(q1), q2, atol=1e-9)
    assert g2.size1 == (400, 300) and g2.size2 == (205, 160)
    # a point mapped to infinity / behind: error inf, never correct; NaN input never correct
    Hinf = np.array([[1.0, 0, 0], [0, 1, 0], [1.0, 0, 0]])
    assert np.isinf(HomographyGT(Hinf).error([[0.0, 5.0]], [[0.0, 0.0]])).all()
    assert not HomographyGT(np.eye(3)).correct([[np.nan, 1.0]], [[1.0, 1.0]]).any()
    assert gt.correct(np.zeros((0, 2)), np.zeros((0, 2))).shape == (0,)


def _random_pose(rng):
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(rng.normal(0, 0.15, 3)).as_matrix()
    t = np.array([1.0, 0.1, 0.05]) + rng.normal(0, 0.05, 3)
    K1 = np.array([[900.0, 0, 320], [0, 880, 240], [0, 0, 1]])
    K2 = np.array([[1000.0, 0, 330], [0, 1010, 250], [0, 0, 1]])
    return K1, K2, R, t


def _project_scene(K1, K2, R, t, rng, n=300):
    X = np.c_[rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(5, 20, n)]  # camera-1 frame
    x1 = X @ K1.T
    X2 = X @ R.T + t
    x2 = X2 @ K2.T
    return x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]


def test_epipolar_gt_rescaled_and_symmetric_distance(rng):
    from guidedmatch.epipolar import point_line_distance

    K1, K2, R, t = _random_pose(rng)
    gt = EpipolarGT.from_pose(K1, K2, R, t)
    p1, p2 = _project_scene(K1, K2, R, t, rng)
    g2 = gt.rescaled(0.5, 2.0)
    assert g2.error(0.5 * (p1 + 0.5) - 0.5, 2.0 * (p2 + 0.5) - 0.5).max() < 1e-6
    # the symmetric distance is the mean of the two one-sided distances, each a true point-line distance
    q2 = p2 + rng.normal(0, 2, p2.shape)
    d2, d1 = point_line_distance(gt.F, p1, q2), point_line_distance(gt.F.T, q2, p1)
    np.testing.assert_allclose(gt.error(p1, q2), 0.5 * (d1 + d2))
    l = np.c_[p1, np.ones(len(p1))] @ gt.F.T
    ref = np.abs(np.sum(np.c_[q2, np.ones(len(q2))] * l, 1)) / np.hypot(l[:, 0], l[:, 1])
    np.testing.assert_allclose(d2, ref, rtol=1e-9)


def _write_pairs_file(root, rng, n_pairs=2):
    import cv2

    d = root / "pose_pairs" / "strecha" / "S" / "images"
    d.mkdir(parents=True)
    lines, poses = [], []
    for k in range(n_pairs + 1):
        cv2.imwrite(str(d / f"{k:04d}.jpg"), np.zeros((48, 64), np.uint8))
    for k in range(n_pairs):
        K1, K2, R, t = _random_pose(rng)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        vals = " ".join(f"{v:.17g}" for v in np.r_[K1.ravel(), K2.ravel(), T.ravel()])
        lines.append(f"S/images/{k:04d}.jpg S/images/{k + 1:04d}.jpg 0 0 {vals}")
        poses.append((K1, K2, R, t))
    (root / "pose_pairs" / "strecha" / "strecha_pairs_with_gt.txt").write_text("\n".join(lines) + "\n")
    return poses


def test_strecha_pairs_parse_the_pairs_format(tmp_path, rng):
    poses = _write_pairs_file(tmp_path, rng)
    pairs = strecha_pairs(tmp_path)
    assert [p.name for p in pairs] == ["strecha/S/0000-0001", "strecha/S/0001-0002"]
    for p, (K1, K2, R, t) in zip(pairs, poses):
        assert p.gt.size1 == (64, 48)
        x1, x2 = _project_scene(K1, K2, R, t, rng)
        h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
        alg = np.abs(np.sum(h2 * (h1 @ p.gt.F.T), axis=1))
        assert alg.max() < 1e-9  # x2^T F x1 = 0 (F has unit norm)
        assert p.gt.error(x1, x2).max() < 1e-6


@pytest.mark.data
@needs_data(*STRECHA_FILES)
def test_strecha_gt_from_the_real_pairs_file_satisfies_epipolar_constraint(rng):
    pairs = strecha_pairs(ROOT, with_sizes=False)
    for p in pairs[::5]:
        g = p.gt
        x1, x2 = _project_scene(g.K1, g.K2, g.R, g.t, rng)
        h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
        assert np.abs(np.sum(h2 * (h1 @ g.F.T), axis=1)).max() < 1e-9
        assert g.error(x1, x2).max() < 1e-5
        assert 3.0 < p.meta["rotation_deg"] < 22.0


@pytest.mark.data
@needs_data(*OXFORD_FILES)
def test_oxford_sizes_and_homographies():
    ox = {p.name: p for p in oxford_pairs(ROOT, sequences=("wall", "bark"), targets=(2, 6))}
    wall = ox["oxford/wall/1-2"]
    assert wall.gt.size1 == (1000, 700) and wall.gt.size2 == (880, 680)  # img2-6 are smaller than img1
    assert wall.sizes == ((1000, 700), (880, 680))
    i1, i2 = wall.load()
    assert i1.shape == (700, 1000) and i2.shape == (680, 880) and i1.dtype == np.uint8
    assert ox["oxford/bark/1-6"].gt.H.shape == (3, 3)
    with pytest.raises(ValueError):
        oxford_pairs(ROOT, sequences=("bikes",), targets=(7,))


# ------------------------------------------------------------------------------------------------
# synthetic generator: GT against a rendered pattern
# ------------------------------------------------------------------------------------------------
def _dot_image(rng, w=640, h=480, radius=6):
    import cv2

    keep = []
    for p in rng.uniform([30, 30], [w - 30, h - 30], (200, 2)):
        if all(np.hypot(*(p - q)) > 40 for q in keep):
            keep.append(p)
    pts = np.array(keep)
    img = np.full((h, w), 255, np.uint8)
    for x, y in pts:  # sub-pixel anti-aliased discs (shift=4: 1/16 px)
        cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), radius * 16, 0, -1, cv2.LINE_AA, shift=4)
    return img, pts


@pytest.mark.parametrize("set_id", [1, 2, 3])
def test_synthetic_homography_maps_dot_centres_within_1px(set_id):
    import cv2
    from scipy import ndimage

    from guidedmatch.alignment import apply_homography

    rng = np.random.default_rng(7)
    img, pts = _dot_image(rng)
    h, w = img.shape
    img2, H, info = synthesize_pair(np.dstack([img] * 3), set_id, rng=100 + set_id)
    assert (img2.shape[1], img2.shape[0]) == info["size2"]
    # nothing is cropped: every corner of image 1 lands inside image 2
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    cw = apply_homography(H, corners, in_front=True)
    W2, H2 = info["size2"]
    assert (cw >= -0.5 - 1e-6).all() and (cw[:, 0] <= W2 - 0.5 + 1e-6).all() and (cw[:, 1] <= H2 - 0.5 + 1e-6).all()
    if set_id == 1:  # the translation is realised as a margin: the content moves by (tx, ty)
        tx, ty = info["translation_px"]
        assert abs(cw[:, 0].min() - (-0.5 + max(tx, 0))) < 1e-6 and abs(cw[:, 1].min() - (-0.5 + max(ty, 0))) < 1e-6
    else:
        assert info["rotation_deg"] != 0.0
    # dot centres (darkness-weighted centroids) in image 2 vs H-projected centres from image 1
    g = cv2.cvtColor(img2, cv2.COLOR_BGR2GRAY).astype(float)
    valid = cv2.warpPerspective(np.ones((h, w), np.uint8), H, info["size2"], flags=cv2.INTER_NEAREST)
    valid = cv2.erode(valid, np.ones((5, 5), np.uint8)) > 0
    bg = np.median(g[valid])
    dark = np.clip(bg - g, 0, None) * valid
    lab, n = ndimage.label(dark > 0.3 * dark.max())
    centres = np.array(ndimage.center_of_mass(dark, lab, range(1, n + 1)))[:, ::-1]  # (x, y)
    proj = apply_homography(H, pts, in_front=True)
    d = np.linalg.norm(proj[:, None] - centres[None], axis=2).min(axis=1)
    assert len(pts) > 30 and d.max() < 1.0, d.max()
    assert np.median(d) < 0.3


def test_synthetic_parameters_stay_in_the_paper_ranges():
    from guidedmatch.datasets import synthetic_homography

    for i in range(200):
        rng = np.random.default_rng([0, 3, i])
        H, size2, info = synthetic_homography((400, 300), 3, rng)
        assert 0.5 <= info["scale"] <= 2.0 and -90 <= info["rotation_deg"] <= 90
        assert np.abs(np.array(info["corner_jitter_px"])).max(axis=0).tolist() <= [20.0, 15.0]
        H1, _, info1 = synthetic_homography((400, 300), 1, np.random.default_rng([0, 1, i]))
        assert abs(info1["translation_px"][0]) <= 40 and abs(info1["translation_px"][1]) <= 30
        assert info1["rotation_deg"] == 0.0 and abs(H1[2, 0]) < 1e-15 and abs(H1[2, 1]) < 1e-15  # affine


def test_colour_transform_keeps_geometry_and_is_seeded():
    from guidedmatch.datasets import colour_transform

    rng = np.random.default_rng(0)
    img = (rng.uniform(0, 255, (60, 80, 3))).astype(np.uint8)
    a, ia = colour_transform(img, np.random.default_rng(5))
    b, ib = colour_transform(img, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert a.shape == img.shape and a.dtype == np.uint8 and ia == ib
    assert 0.8 <= ia["pca_contrast"] <= 1.2 and -0.05 <= ia["hue_add"] <= 0.05
    assert 0.5 <= ia["saturation"]["power"] <= 2.0 and 0.8 <= ia["value"]["mult"] <= 1.2
    g, _ = colour_transform(img[:, :, 0], np.random.default_rng(5))
    assert g.shape == (60, 80)


@pytest.mark.data
@needs_data(*PHOTO_FILES)
def test_synthetic_photos_are_reused_with_different_transforms():
    from guidedmatch.datasets import list_photos, synthetic_pair

    n = len(list_photos(ROOT))
    assert n == 24
    a = synthetic_pair(ROOT, 3, 0, seed=0, max_side=300)
    b = synthetic_pair(ROOT, 3, n, seed=0, max_side=300)
    c = synthetic_pair(ROOT, 3, 0, seed=1, max_side=300)
    assert a.meta["photo"] == b.meta["photo"] == c.meta["photo"]
    assert not np.allclose(a.gt.H, b.gt.H) and not np.allclose(a.gt.H, c.gt.H)
    np.testing.assert_array_equal(a.image1, b.image1)
    assert max(a.image1.shape[:2]) == 300 and a.gt.size2 == (a.image2.shape[1], a.image2.shape[0])


# ------------------------------------------------------------------------------------------------
# GT decisions with the shared geometry functions (epipolar / alignment) vs the formulas datasets used before
# ------------------------------------------------------------------------------------------------
def _legacy_projection(H, p):
    """The projection datasets.project_homography computed before the merge: a (N, 2) @ (2, 3) matrix product."""
    hom = p @ H[:, :2].T + H[:, 2]
    w = hom[:, 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = hom[:, :2] / w
    out[(w[:, 0] <= 0) | ~np.isfinite(out).all(axis=1)] = np.nan
    return out


def _legacy_homography_correct(gt, p1, p2, thr=3.0):
    proj = _legacy_projection(gt.H, p1)
    e = np.linalg.norm(proj - p2, axis=1)
    e[~np.isfinite(e)] = np.inf

    def inside(p, size):
        w, h = size
        with np.errstate(invalid="ignore"):
            return (p[:, 0] >= -0.5) & (p[:, 0] <= w - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] <= h - 0.5)

    return e, (e < thr) & inside(p1, gt.size1) & inside(proj, gt.size2)


def _legacy_symmetric_epipolar(F, p1, p2):
    """datasets.symmetric_epipolar_distance before the merge: |x2^T F x1| over each line's normal, inf if undefined."""
    x1, x2 = np.c_[p1, np.ones(len(p1))], np.c_[p2, np.ones(len(p2))]
    l2, l1 = x1 @ F.T, x2 @ F
    alg = np.abs(np.sum(x2 * l2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 0.5 * (alg / np.hypot(l1[:, 0], l1[:, 1]) + alg / np.hypot(l2[:, 0], l2[:, 1]))
    d[~np.isfinite(d)] = np.inf
    return d


@pytest.mark.data
@needs_data(*OXFORD_FILES, *STRECHA_FILES)
def test_gt_decisions_unchanged_by_the_shared_geometry_functions():
    """HomographyGT / EpipolarGT now use alignment.apply_homography and epipolar.symmetric_epipolar_distance
    (element-wise products, normalised lines) instead of their own copies. On the real GT (12 Oxford pairs,
    18 Herz-Jesus pairs) and 40 000 random points per pair -- a quarter of them placed 3 px +- 1e-9..1e-3 px from
    the GT position, i.e. next to the 3 px threshold -- every correctness decision must be the same."""
    rng = np.random.default_rng(0)
    n_points = 0
    for p in oxford_pairs(ROOT):
        gt = p.gt
        w, h = gt.size1
        p1 = rng.uniform([-20, -20], [w + 20, h + 20], (40_000, 2))  # some outside image 1
        ang = rng.uniform(0, 2 * np.pi, len(p1))
        r = rng.uniform(0, 6, len(p1))
        near = rng.random(len(p1)) < 0.25
        r[near] = 3.0 + rng.choice([-1, 1], near.sum()) * 10.0 ** rng.uniform(-9, -3, near.sum())
        p2 = _legacy_projection(gt.H, p1) + r[:, None] * np.c_[np.cos(ang), np.sin(ang)]
        e_old, ok_old = _legacy_homography_correct(gt, p1, p2)
        ok = gt.correct(p1, p2)
        np.testing.assert_array_equal(ok, ok_old)
        e = gt.error(p1, p2)
        fin = np.isfinite(e_old)
        np.testing.assert_array_equal(np.isfinite(e), fin)
        assert np.abs(e[fin] - e_old[fin]).max() < 1e-10
        assert 0.2 < ok.mean() < 0.8 and ok[near].any() and not ok[near].all()
        n_points += len(p1)
    for p in strecha_pairs(ROOT):
        gt = p.gt
        w, h = gt.size1
        p1 = rng.uniform([-20, -20], [w + 20, h + 20], (40_000, 2))
        p2 = rng.uniform([-20, -20], [w + 20, h + 20], (40_000, 2))
        # move a half of the image-2 points to within 0..8 px of their epipolar line
        line = np.c_[p1, np.ones(len(p1))] @ gt.F.T
        nrm = line[:, :2] / np.hypot(line[:, 0], line[:, 1])[:, None]
        dist = np.sum(np.c_[p2, np.ones(len(p2))] * line, axis=1) / np.hypot(line[:, 0], line[:, 1])
        half = rng.random(len(p1)) < 0.5
        p2[half] -= (dist[half] - rng.uniform(-8, 8, half.sum()))[:, None] * nrm[half]
        d_old = _legacy_symmetric_epipolar(gt.F, p1, p2)
        ok_old = (d_old < 3.0) & (p1[:, 0] >= -0.5) & (p1[:, 0] <= w - 0.5) & (p1[:, 1] >= -0.5) & (p1[:, 1] <= h - 0.5)
        w2, h2 = gt.size2
        ok_old &= (p2[:, 0] >= -0.5) & (p2[:, 0] <= w2 - 0.5) & (p2[:, 1] >= -0.5) & (p2[:, 1] <= h2 - 0.5)
        np.testing.assert_array_equal(gt.correct(p1, p2), ok_old)
        d = gt.error(p1, p2)
        assert np.isfinite(d).all() and np.abs(d - d_old).max() < 1e-9
        assert 0.05 < ok_old.mean() < 0.5
        n_points += len(p1)
    assert n_points == 30 * 40_000
