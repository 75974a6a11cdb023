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
