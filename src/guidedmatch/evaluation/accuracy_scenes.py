"""The scenes of the accuracy benchmark: where their images and reference poses are, how far those poses can be
trusted, and the database copy both the benchmark and its analysis use."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from .poses import CameraPose, read_cameras_txt, read_strecha_cameras

__all__ = ["SCENES", "scene_paths", "reference_cameras", "distortion", "copy_database"]

#: scene -> (folder under the data root, reference kind, how far the reference can be trusted)
SCENES = {
    "Herz-Jesus-P8": ("pose_pairs/strecha/Herz-Jesus-P8", "strecha",
                      "ground truth (Strecha et al., laser-scan registered)"),
    "Herz-Jesus-P25": ("collections/Herz-Jesus-P25", "cameras.txt", "ground truth (Strecha et al.)"),
    "buddha": ("collections/buddha", "cameras.txt",
               "SfM estimate of the dataset authors (AliceVision): sub-pixel epipolar agreement with SIFT matches, "
               "not independent ground truth; image 00065 only weakly constrained"),
    "fox": ("collections/fox", "cameras.txt",
            "COLMAP estimate shipped with instant-ngp (lens distortion k1 0.058): not independent of COLMAP, so it "
            "favours COLMAP's own matches"),
}

def scene_paths(root: Path, scene: str) -> tuple[Path, Path]:
    """``(image folder, scene folder)`` of a scene under the data root."""
    folder = Path(root) / SCENES[scene][0]
    return folder / "images", folder


def reference_cameras(root: Path, scene: str) -> dict[str, CameraPose]:
    """``{image name: CameraPose}`` of a scene's reference poses."""
    _, folder = scene_paths(root, scene)
    if SCENES[scene][1] == "strecha":
        return read_strecha_cameras(folder / "gt_dense_cameras")
    return read_cameras_txt(folder / "cameras.txt")


def distortion(root: Path, scene: str) -> np.ndarray | None:
    """OpenCV distortion coefficients of a scene's images (``distortion.txt``: ``k1 k2 p1 p2``), None when absent."""
    path = scene_paths(root, scene)[1] / "distortion.txt"
    if not path.is_file():
        return None
    vals = {}
    for tok in path.read_text().replace("=", " ").replace(",", " ").split():
        vals.setdefault("_", []).append(tok)
    nums = []
    for tok in vals.get("_", []):
        try:
            nums.append(float(tok))
        except ValueError:
            pass
    if len(nums) < 4:
        raise ValueError(f"{path}: expected k1 k2 p1 p2")
    return np.array(nums[:4], np.float64)


def copy_database(src: Path, dst: Path) -> None:
    """Copy a SQLite database after folding its write-ahead log into it (a copy of the main file alone would miss
    the log's pages)."""
    import sqlite3

    con = sqlite3.connect(str(src))
    try:
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    finally:
        con.close()
    shutil.copyfile(src, dst)
