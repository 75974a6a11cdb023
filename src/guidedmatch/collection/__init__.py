"""Match whole image collections: feature sources, pair lists and match sinks (COLMAP / hloc files).

``sources``: :class:`ColmapSource`, :class:`H5Source`, :func:`open_source`, :func:`images_to_database`.
``pairs``: :class:`PairList`, :func:`exhaustive_pairs`, :func:`sequential_pairs`, :func:`read_pairs_file`,
:func:`pairs_from_spec`.
``sinks``: :class:`ColmapSink`, :class:`H5MatchesSink`, :func:`cap_two_view_inliers`,
:func:`tighten_two_view_inliers`.
"""
from __future__ import annotations

from .pairs import (Pair, PairList, exhaustive_pairs, normalize_pairs, pairs_from_spec, read_pairs_file,
                    sequential_pairs, write_pairs_file)
from .sinks import ColmapSink, H5MatchesSink, MatchSink, cap_two_view_inliers, names_to_pair, tighten_two_view_inliers
from .sources import (ColmapSource, FeatureSource, H5Source, images_to_database, open_source,
                      write_features_h5)

__all__ = ["FeatureSource", "ColmapSource", "H5Source", "open_source", "images_to_database", "write_features_h5",
           "Pair", "PairList", "exhaustive_pairs", "sequential_pairs", "read_pairs_file", "pairs_from_spec",
           "normalize_pairs", "write_pairs_file", "MatchSink", "ColmapSink", "H5MatchesSink", "names_to_pair",
           "cap_two_view_inliers", "tighten_two_view_inliers"]
