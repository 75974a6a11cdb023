"""Regenerate the SfM section of the benchmark summary page (docs/benchmarks.md): COLMAP's matcher vs guidedmatch
inside COLMAP's mapper, and end to end from an empty folder, from benchmarks/results/sfm/sfm.json.

    python tools/readme_sfm.py            (after: guidedmatch bench sfm --out benchmarks/results/sfm)

The section sits between ``<!-- sfm:start -->`` and ``<!-- sfm:end -->`` in docs/benchmarks.md; without the markers
it is appended at the end. ``--print`` writes it to stdout instead. Links are relative to docs/. How to use
``guidedmatch sfm`` and the inlier cap is described in docs/sfm.md (hand-written).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
START, END = "<!-- sfm:start -->", "<!-- sfm:end -->"

def section(results: dict) -> str:
    """The marked benchmark-page section for one ``sfm.json``."""
    from guidedmatch.evaluation.bench_sfm import e2e_table, markdown_table

    meta = results.get("meta", {})
    lines = [START, "## COLMAP's matcher vs guidedmatch inside COLMAP's mapper (Herz-Jesus-P8, ground-truth poses)", "",
             "Same pycolmap SIFT features in every row (one extraction copied per method), CPU, "
             f"{results.get('threads', '?')} threads; `pycolmap.incremental_mapping` on each database; pose error = "
             "max(rotation, translation-direction) error of the relative pose of every image pair against the "
             "Strecha GT cameras (unregistered images count as failures), AUC = area under the recall curve up to "
             "1/2/5 deg. `+ours` = our two-view geometries written directly; `+colmap` = our matches verified by "
             "COLMAP (time shown as match + verify); `+cap` = then at most 1000 inliers per pair handed to the mapper "
             "(spread, best first: what `guidedmatch sfm` does; its verified inliers are what the mapper got). Wrong inliers (COLMAP's model): verified inliers whose partner "
             "lies > 10 px from where the model mapped from COLMAP's exhaustive matches of the same run puts it (the "
             "3-D point of one keypoint projected into the other image: a wrong match on the right epipolar line "
             "passes F but not this check; `guidedmatch.evaluation.consistency`); est. correct = verified inliers x "
             "the share within 3 px, relative to COLMAP's.", "",
             markdown_table(results["rows"]).rstrip(), "",
             *(["End to end from an empty folder (8192 features; `guidedmatch sfm` with its defaults vs the same "
                "pycolmap pipeline with COLMAP's matcher, each a fresh process timed from start to exit, imports "
                "included):", "", e2e_table(results["end_to_end"]), ""]
               if results.get("end_to_end") else []),
             _runs_note(results),
             f"Last run: `{results.get('command', 'guidedmatch bench sfm')}` (commit "
             f"`{str(meta.get('git_commit'))[:10]}`{' + local changes' if meta.get('git_dirty') else ''}, "
             f"{str(meta.get('timestamp_utc', ''))[:16]} UTC, {meta.get('cpu_model')}), then "
             "`python tools/readme_sfm.py`. Rows kept from earlier runs (`--merge`, see the finish times) may have "
             "run while the machine was shared with other jobs: compare times within one run; inlier counts, "
             "registrations and pose errors are exact for each run. Raw numbers: "
             "[benchmarks/results/sfm/sfm.json](../benchmarks/results/sfm/sfm.json), plot: "
             "[sfm_time_vs_inliers.png](../benchmarks/results/sfm/sfm_time_vs_inliers.png); the history of these "
             "measurements: [sfm/history.md](../benchmarks/results/sfm/history.md).", END]
    return "\n".join(lines) + "\n"


def _runs_note(results: dict) -> str:
    """When each row finished (``--merge`` keeps rows of earlier runs; each row has its own timestamp)."""
    stamps = sorted((str(r.get("timestamp_utc", "?"))[11:16], f"{r['method']} ({r['setting']})") for r in results["rows"])
    return ("Row finish times (UTC; rows of one setting finishing minutes apart come from one run, `--merge` kept "
            "earlier rows): " + ", ".join(f"{m} {t}" for t, m in stamps) + ".")


def splice(readme: str, text: str) -> str:
    """Replace the marked section of ``readme`` by ``text`` (append it when the markers are missing)."""
    if START in readme and END in readme:
        i, j = readme.index(START), readme.index(END) + len(END)
        return readme[:i] + text.rstrip("\n") + readme[j:]
    return readme.rstrip("\n") + "\n\n" + text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default=str(ROOT / "benchmarks" / "results" / "sfm" / "sfm.json"))
    ap.add_argument("--target", "--readme", dest="readme", default=str(ROOT / "docs" / "benchmarks.md"),
                    help="the page to update (default docs/benchmarks.md)")
    ap.add_argument("--print", action="store_true", help="print the section instead of writing the page")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "src"))
    text = section(json.loads(Path(args.results).read_text()))
    if args.print:
        print(text)
        return 0
    readme = Path(args.readme)
    readme.write_text(splice(readme.read_text(), text))
    print(f"wrote the sfm section of {readme}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
