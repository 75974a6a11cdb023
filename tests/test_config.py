import math
from typing import get_args

import pytest
from hypothesis import given
from hypothesis import strategies as st

from guidedmatch.config import MODES, Alignment, MatcherConfig, Mode, RansacMethod
from guidedmatch.errors import ConfigError
from guidedmatch.validation import config_from

NAN, INF = float("nan"), float("inf")

# the bad values a user is likely to pass first, then a range / type / NaN violation for every field
BAD = [
    ("band_px", NAN), ("so_threshold", -1), ("so_threshold", NAN), ("ransac_threshold", -1), ("seed", 1.5),
    ("max_distance", -1), ("ransac_method", "magsca"),
    ("num_groups", 0), ("num_groups", 2.0), ("update_every", 7), ("num_updates", -1), ("so_threshold", 0.0),
    ("so_threshold", 1.0), ("band_px", 0.0), ("band_px", INF), ("band_px", "5"), ("alignment", "z"),
    ("ratio", 0.0), ("ratio", 1.5), ("ratio", NAN), ("single_candidate", "maybe"), ("mutual", 1), ("one_to_one", 0),
    ("one_to_one", "yes"), ("max_distance", NAN), ("ransac_threshold", INF), ("so_overlap", "k3d"),
    ("batch_size", 0), ("strip_px", 0.0), ("strip_px", -3.0), ("recheck", "true"), ("outside_window", "keep"),
    ("min_model_matches", 7), ("seed", -1), ("seed", True), ("frame_hypotheses", 1), ("frame_hypotheses", "on"),
]


@pytest.mark.parametrize("name,value", BAD)
def test_every_bad_value_raises_config_error_at_construction(name, value):
    with pytest.raises(ConfigError, match=rf"MatcherConfig\.{name} must be .*; got "):
        MatcherConfig(**{name: value})
    with pytest.raises(ValueError):  # ConfigError is a ValueError
        MatcherConfig().replace(**{name: value})


def test_choice_errors_list_the_valid_values():
    with pytest.raises(ConfigError) as e:
        MatcherConfig(ransac_method="magsca")
    assert all(repr(m) in str(e.value) for m in get_args(RansacMethod))


def test_unknown_names_are_listed_with_the_valid_ones():
    with pytest.raises(ConfigError, match="unknown MatcherConfig option.*bandpx.*valid: .*band_px"):
        config_from(MatcherConfig, {"bandpx": 3})
    with pytest.raises(ConfigError, match="so_probability"):  # removed: the gap table uses the Gaussian model only
        MatcherConfig().replace(so_probability="exact")


def test_defaults_and_paper_config_are_valid():
    c = MatcherConfig()
    assert c.one_to_one is None and not c.mutual
    p = MatcherConfig.paper()
    assert (p.recheck, p.outside_window, p.one_to_one) == (False, "drop", False)
    assert config_from(MatcherConfig, {"band_px": 3}) == MatcherConfig(band_px=3)
    assert config_from(MatcherConfig, c) is c


def test_literals_match_the_estimators():
    from guidedmatch.alignment import APPROACHES
    from guidedmatch.epipolar import USAC_METHODS

    assert get_args(Alignment) == APPROACHES
    assert set(get_args(RansacMethod)) == set(USAC_METHODS)


@given(so=st.booleans(), epi=st.booleans(), ia=st.booleans())
def test_mode_parse_is_the_one_definition(so, epi, ia):
    name = "+".join(p for p, on in (("so", so), ("epi", epi), ("ia", ia)) if on) or "bf"
    if name not in MODES:  # "ia" without "so+epi" is no mode of the paper
        with pytest.raises(ConfigError, match="unknown mode.*so\\+epi\\+ia"):
            Mode.parse(name)
        return
    m = Mode.parse(name.upper())
    assert (m.name, m.use_so, m.use_epi, m.use_ia, m.guided) == (name, so, epi, ia, name != "bf")
    assert Mode.parse(m) is m


def test_one_to_one_meaning_per_mode():
    bf, guided = Mode.parse("bf"), Mode.parse("so+epi+ia")
    assert not MatcherConfig().one_to_one_in(bf) and MatcherConfig().one_to_one_in(guided)
    for v in (True, False):
        c = MatcherConfig(one_to_one=v)
        assert c.one_to_one_in(bf) is v and c.one_to_one_in(guided) is v


@given(band=st.floats(allow_nan=True, allow_infinity=True), th=st.floats(allow_nan=True, allow_infinity=True))
def test_float_fields_accept_exactly_their_ranges(band, th):
    ok = math.isfinite(band) and band > 0 and math.isfinite(th) and 0 < th < 1
    if ok:
        assert MatcherConfig(band_px=band, so_threshold=th).band_px == band
    else:
        with pytest.raises(ConfigError):
            MatcherConfig(band_px=band, so_threshold=th)
