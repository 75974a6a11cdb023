"""guidedmatch: guided image feature matching with feature spatial order (Teng & Dong) and epipolar geometry."""
from __future__ import annotations

__version__ = "0.1.0"

from .results import Failure, MatchResult

__all__ = ["Failure", "MatchResult", "__version__"]
