"""Counts and hashes of a behaviour capture, to compare two versions of the code on one machine.

A capture folder holds the outputs of one version (written by ``tools/behaviour_capture.sh CHECKOUT OUT``, which runs,
with that version on PYTHONPATH):
``guidedmatch demo > demo.txt``, ``guidedmatch bench oxford --quick --out oxford``, ``guidedmatch bench pairs
--features 8192 --out pairs --repeats 1`` and ``colmap_hash.txt`` (sha256 of the ``matches`` and
``two_view_geometries`` tables of a ``guidedmatch colmap`` database, rows ordered by pair_id). This prints, for each
output, the counts that must not change (never times) and a sha256 over them, so two captures compare line by line::

    python tools/behaviour_hash.py /tmp/before/out
    python tools/behaviour_hash.py /tmp/before/out /tmp/after/out   # both, then the lines that differ
"""
from __future__ import annotations

import hashlib
import json
import re
import sys
from pathlib import Path

# demo table rows: mode, comparisons, % of BF, matches, true, precision, time (s) -- the time is left out
_DEMO_ROW = re.compile(r"^(bf|epi|so|so\+epi|so\+epi\+ia)\s+([\d,]+)\s+([\d.]+)%\s+(\d+)\s+(\d+)\s+([\d.]+)%\s+[\d.]+\s*$")
_OXFORD_KEYS = ("comparisons", "matches", "true")
_PAIRS_KEYS = ("comparisons", "matches", "gt_inliers", "wrong", "verdict", "verdict_model", "verdict_inliers",
               "verdict_gt_inliers")


def _digest(lines: list[str]) -> str:
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()[:16]


def demo_lines(folder: Path) -> list[str]:
    out = []
    for line in (folder / "demo.txt").read_text().splitlines():
        m = _DEMO_ROW.match(line.strip())
        if m:
            out.append("demo " + " ".join(m.groups()))
    return out


def oxford_lines(folder: Path) -> list[str]:
    res = json.loads((folder / "oxford" / "results.json").read_text())
    out = []
    for row in res["oxford"]:
        for method, v in sorted(row["methods"].items()):
            out.append(f"oxford {row['name']} {method} " + " ".join(f"{k}={v.get(k)}" for k in _OXFORD_KEYS))
    return out


def pairs_lines(folder: Path) -> list[str]:
    res = json.loads((folder / "pairs" / "pairs.json").read_text())
    out = []
    for set_name, s in sorted(res["sets"].items()):
        for row in s["rows"]:
            for method, v in sorted(row["methods"].items()):
                if not isinstance(v, dict):
                    continue
                out.append(f"pairs {set_name} {row['name']} {method} "
                           + " ".join(f"{k}={v.get(k)}" for k in _PAIRS_KEYS if k in v))
    return out


def colmap_lines(folder: Path) -> list[str]:
    return ["colmap " + line.strip() for line in (folder / "colmap_hash.txt").read_text().splitlines() if line.strip()]


def capture(folder: Path) -> dict[str, list[str]]:
    return {name: fn(folder) for name, fn in (("demo", demo_lines), ("oxford", oxford_lines), ("pairs", pairs_lines),
                                               ("colmap", colmap_lines))}


def main(argv: list[str]) -> int:
    if not argv or len(argv) > 2:
        print(__doc__)
        return 2
    caps = [capture(Path(a)) for a in argv]
    for a, cap in zip(argv, caps):
        print(f"# {a}")
        for name, lines in cap.items():
            print(f"{name:7s} {len(lines):4d} lines  sha256 {_digest(lines)}")
        for line in cap["colmap"]:
            print("   ", line)
    if len(caps) == 2:
        same = True
        for name in caps[0]:
            a, b = caps[0][name], caps[1][name]
            if a == b:
                print(f"{name}: identical")
                continue
            same = False
            sa, sb = set(a), set(b)
            print(f"{name}: {len(sa - sb)} lines only in the first, {len(sb - sa)} only in the second")
            for line in sorted(sa - sb)[:20]:
                print("  -", line)
            for line in sorted(sb - sa)[:20]:
                print("  +", line)
        print("IDENTICAL" if same else "DIFFERENT")
        return 0 if same else 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
