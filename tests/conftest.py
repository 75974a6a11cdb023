import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


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
