"""Regenerate the README "Use it in COLMAP" section (commands + the sfm benchmark table) from
benchmarks/results/sfm/sfm.json.

    python tools/readme_sfm.py            (after: guidedmatch bench sfm --out benchmarks/results/sfm)

The section sits between ``<!-- sfm:start -->`` and ``<!-- sfm:end -->`` in README.md; without the markers it is
appended at the end. ``--print`` writes it to stdout instead.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
START, END = "<!-- sfm:start -->", "<!-- sfm:end -->"

USAGE = """## Use it in COLMAP

guidedmatch replaces COLMAP's matching step and leaves extraction and mapping to COLMAP. With an existing COLMAP
project (or a fresh `colmap feature_extractor` run), the three commands are:

```bash
colmap feature_extractor --database_path project/database.db --image_path photos/     # COLMAP's SIFT, as usual
guidedmatch colmap project/database.db --pairs exhaustive     # matches + two-view geometries into the database
colmap mapper --database_path project/database.db --image_path photos/ --output_path project/sparse
```

`guidedmatch colmap` writes the `matches` and `two_view_geometries` tables, so the mapper needs no separate
`colmap matches_importer` / verification step; `--pairs sequential:10` or `--pairs pairs.txt` (COLMAP / hloc
`name1 name2` lines) instead of exhaustive, `--workers N` or `--scheduler ADDRESS` (Dask) for large sets; a
rerun skips the pairs already in the database. Or everything in one command, with pycolmap doing extraction and
mapping:

```bash
guidedmatch sfm photos/ project/            # -> project/database.db, project/sparse/0, report.md, reconstruction.png
colmap gui --database_path project/database.db --image_path photos/ --import_path project/sparse/0
```

`--camera PINHOLE:fx,fy,cx,cy` for known intrinsics, `--single-camera`, `--max-features N`, `--detector ours:orb`,
`--geometry colmap` to let COLMAP verify our matches instead of writing our two-view geometries.

**The mapper gets at most 1000 inliers per pair.** COLMAP's mapper spends its time in bundle adjustments whose cost
follows the observations it triangulates, and a pair with thousands of verified inliers fixes a pose no better than
a thousand of its best, well spread ones. `guidedmatch sfm` therefore keeps, per image pair, at most
`--max-inliers-per-pair K` (default 1000; `0` = all) of the verified inliers for the mapper: a 16 x 16 grid over
image 1, the smallest descriptor distance of each cell first, round after round (`gm.spread_matches`).
Pairs with fewer inliers are untouched, so the weak links of the view graph stay whole; the `matches` table keeps
every raw match. On Herz-Jesus-P8 this made mapping 2.6x faster at 8192 features and 16x at ~68k, with poses at
least as accurate as with all inliers (median pose error 0.207 -> 0.164 deg at 8192; 0.207 -> 0.166-0.194 deg at
~68k, where the mapper itself varies run to run): the `+cap` rows below, and the sweep in
[docs/collections.md](docs/collections.md#how-many-inliers-the-mapper-needs). It is what makes `guidedmatch sfm`
faster end to end than the same pipeline with COLMAP's matcher (last table). `guidedmatch colmap` writes every
inlier unless given `--max-inliers-per-pair 1000`, and `gm.cap_two_view_inliers(db, 1000)` applies the
same selection to any COLMAP database (COLMAP's own matches included). Below 100, COLMAP's mapper cannot choose an
initial pair (`init_min_num_inliers`); `sfm` refuses such values.

In Python, **import guidedmatch (or NumPy) before pycolmap or hloc**. pycolmap 4.2.1's wheel carries its own zlib
and exports it; when `import pycolmap` (or `import hloc`, which imports it) is the first thing a process does, the
system zlib gets bound to that copy and the next PNG, `np.savez_compressed` or gzip write aborts the process
(`free(): invalid pointer`). `import guidedmatch` loads the system zlib first; imported after pycolmap it warns
(`RuntimeWarning`) if the process is already affected, and its own writers then raise `OutputError` instead of
aborting (`guidedmatch._runtime.zlib_shadowed`, tested in a fresh interpreter in `tests/test_runtime.py`).
"""


def section(results: dict) -> str:
    """The marked README section for one ``sfm.json``."""
    from guidedmatch.evaluation.bench_sfm import e2e_table, markdown_table

    meta = results.get("meta", {})
    lines = [START, USAGE,
             "### COLMAP's matcher vs guidedmatch inside COLMAP's mapper (Herz-Jesus-P8, ground-truth poses)", "",
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
             "[benchmarks/results/sfm/sfm.json](benchmarks/results/sfm/sfm.json), plot: "
             "[sfm_time_vs_inliers.png](benchmarks/results/sfm/sfm_time_vs_inliers.png).", END]
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
    ap.add_argument("--readme", default=str(ROOT / "README.md"))
    ap.add_argument("--print", action="store_true", help="print the section instead of writing the README")
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
