"""Evaluation data: image pairs with ground truth (Teng & Dong, Sec. IV).

Three sources, all read in place from the shared data folder (see ``../shared/data/SOURCES.md``):

* :func:`oxford_pairs` -- Oxford affine-covariant sequences (Sec. IV-A), ground truth = the
  dataset homography ``H1toN`` (:class:`HomographyGT`).
* :func:`strecha_pairs` -- real high-resolution pairs (Strecha Herz-Jesus-P8) with ground-truth
  intrinsics and relative pose (:class:`EpipolarGT`); stands in for the paper's real images (Sec. IV-C),
  for which the paper had no ground truth.
* :func:`synthetic_pairs` -- the simulated set of Sec. IV-B (after Dosovitskiy et al. 2016, plus a
  perspective warp), generated lazily and deterministically from ``photos/unsplash/``; ground truth = the
  generated homography.

Coordinates follow the package convention: pixels, origin at the *centre* of the top-left pixel,
x right, y down, arrays ``(N, 2) float64``. An image of width ``w`` covers ``x in [-0.5, w - 0.5]``.

The data root is the one configurable path (:func:`data_root`): an explicit override, else the
environment variable ``GUIDEDMATCH_DATA``, else ``../shared/data`` relative to the current directory or
to the repository root.

Code: :mod:`.root` (the data folder, file reading, the photo folder), :mod:`.ground_truth` (:class:`HomographyGT`,
:class:`EpipolarGT`, :class:`Pair`), :mod:`.real` (Oxford, Strecha), :mod:`.synthetic` (the simulated set); every
name is found here.
"""
from __future__ import annotations

from .ground_truth import DEFAULT_THRESHOLD, EpipolarGT, GroundTruth, HomographyGT, Pair
from .real import (OXFORD_ALL_SEQUENCES, OXFORD_SEQUENCES, STRECHA_PAIRS_FILE, STRECHA_SCENE_DIR, StrechaCamera,
                   camera_angles, oxford_pairs, read_strecha_camera, relative_pose, strecha_pairs, strecha_scene_pairs)
from .root import ENV_VAR, PHOTOS_DIR, data_root, list_photos
from .synthetic import (SYNTHETIC_SETS, SyntheticParams, colour_transform, synthesize_pair, synthetic_homography,
                        synthetic_pair, synthetic_pairs)

__all__ = ["ENV_VAR", "DEFAULT_THRESHOLD", "OXFORD_SEQUENCES", "OXFORD_ALL_SEQUENCES", "STRECHA_PAIRS_FILE",
           "STRECHA_SCENE_DIR", "PHOTOS_DIR", "data_root", "list_photos", "HomographyGT", "EpipolarGT", "GroundTruth",
           "Pair", "oxford_pairs", "strecha_pairs", "StrechaCamera", "read_strecha_camera", "relative_pose",
           "camera_angles", "strecha_scene_pairs", "SYNTHETIC_SETS", "SyntheticParams", "synthetic_homography",
           "colour_transform", "synthesize_pair", "synthetic_pair", "synthetic_pairs"]
