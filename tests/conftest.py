import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

# no per-example time limit: the machines are shared, and hypothesis's 200 ms deadline failed a 16-row h5 round trip
# at load 9 (472 ms); speed is measured in the benchmarks, not asserted in tests
from hypothesis import settings as _hypothesis_settings  # noqa: E402

_hypothesis_settings.register_profile("guidedmatch", deadline=None)
_hypothesis_settings.load_profile("guidedmatch")


@pytest.fixture(scope="session")
def small_scene():
    """A 640x480 rendered two-view scene with 25 deg roll (exact GT)."""
    from guidedmatch.testing.scenes import make_scene

    return make_scene((640, 480), roll_deg=25.0, seed=3)


@pytest.fixture(scope="session")
def small_scene_features(small_scene):
    from guidedmatch.features import detect

    return detect(small_scene.image1), detect(small_scene.image2)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def five_views(tmp_path_factory):
    """5 rendered overlapping views (640x480, seed 0, known K / R / t) written as PNG files: ``(scene, folder)``,
    shared by the extraction, sfm and sfm-benchmark tests -- read only (a test that adds files copies the folder)."""
    mv = pytest.importorskip("guidedmatch.testing.multiview")
    scene = mv.make_multiview(n_views=5, size=(640, 480), seed=0, isolated=False)
    folder = tmp_path_factory.mktemp("five_views") / "images"
    mv.write_views(scene, folder)
    return scene, folder


# ------------------------------------------------------------------------------------------------ collections
@pytest.fixture(scope="session")
def sequence_db(tmp_path_factory):
    """A COLMAP database, features only (no pair matched yet), of one rendered sequence: 6 overlapping views + 1
    view looking away (480x360, seed 3). Shared by the expansion and second-look tests: copy it before writing."""
    from guidedmatch.collection.sources import images_to_database
    from guidedmatch.testing.multiview import make_multiview, write_views

    d = tmp_path_factory.mktemp("sequence")
    mv = make_multiview(6, (480, 360), seed=3, isolated=True, spacing=1.0)
    write_views(mv, d / "img")
    images_to_database(d / "img", d / "db.db", progress=False).close()
    return d / "db.db"


class CrashingSink:
    """A sink stand-in that raises ``KeyboardInterrupt`` after ``n`` writes (a crash mid-run); everything else is
    the wrapped sink's."""

    def __init__(self, sink, n: int):
        self._sink, self.n = sink, n

    def __getattr__(self, name):
        return getattr(self._sink, name)

    def write(self, *a, **k):
        if self.n <= 0:
            raise KeyboardInterrupt("simulated crash")
        self.n -= 1
        return self._sink.write(*a, **k)


@pytest.fixture
def crashing_sink():
    """``crashing_sink(n)``: a sink wrapper, ``sink -> CrashingSink(sink, n)`` (it crashes after ``n`` writes)."""
    return lambda n: (lambda sink: CrashingSink(sink, n))
