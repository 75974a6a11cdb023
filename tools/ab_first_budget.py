"""tools/ab_first_budget.py SCENE ROUNDS [VARIANTS]: matching time of settings of the first pass and the second look on
fresh copies of a scene's cached COLMAP features (bench accuracy's cache), each a fresh process, alternating order per
round, against pycolmap.match_exhaustive; prints one JSON line per run (wall, CPU of the children, steal seconds of the
machine during the run, verified pairs / inliers).

Variants: ``defaults`` (`guidedmatch colmap DB`), ``no_second_look``, and ``first=F,look=JSON``: the first pass with
``max_unguided=F``, then the second look with ``SecondLookConfig(**JSON)`` (one process, the path of
``guidedmatch colmap``: sfm.stages.match_into_database)."""
import json, os, resource, shutil, subprocess, sys, time
from pathlib import Path

PY = sys.executable
CACHE = Path(os.path.expanduser("~/.cache/guidedmatch/accuracy"))
VARIANT_CODE = """
import sys, json
from guidedmatch.collection.config import CollectionConfig
from guidedmatch.collection.sources import ColmapSource
from guidedmatch.collection.pairs import pairs_from_spec
from guidedmatch.config import MatcherConfig
from guidedmatch.sfm.stages import match_into_database
db, first, look = sys.argv[1], float(sys.argv[2]), json.loads(sys.argv[3])
src = ColmapSource(db)
cconf = CollectionConfig(matcher=MatcherConfig(max_unguided=first), progress=False)
match_into_database(src, pairs_from_spec("exhaustive", src.names()), db, cconf, second_look=look)
"""
COLMAP_CODE = """
import pycolmap, sys
o = pycolmap.FeatureMatchingOptions(); o.num_threads = 2
pycolmap.match_exhaustive(sys.argv[1], matching_options=o, device=pycolmap.Device.cpu)
"""


def steal():
    return int(open("/proc/stat").readline().split()[8]) / os.sysconf("SC_CLK_TCK")


def command(v, db):
    if v == "defaults":
        return [PY, "-m", "guidedmatch.cli", "colmap", db, "--no-progress", "--log", "none"]
    if v == "no_second_look":
        return [PY, "-m", "guidedmatch.cli", "colmap", db, "--no-progress", "--log", "none", "--no-second-look"]
    if v == "colmap":
        return [PY, "-c", COLMAP_CODE, db]
    first, look = v.split(",look=")
    return [PY, "-c", VARIANT_CODE, db, first.removeprefix("first="), look]


def main():
    scene, rounds = sys.argv[1], int(sys.argv[2])
    variants = sys.argv[3].split(";") if len(sys.argv) > 3 else ["defaults", "colmap"]
    from guidedmatch.sfm import verified_inliers
    for r in range(rounds):
        for v in (variants if r % 2 == 0 else variants[::-1]):
            db = f"/tmp/ab_first_{os.getpid()}.db"
            for p in Path("/tmp").glob(Path(db).name + "*"):
                p.unlink()
            shutil.copyfile(CACHE / scene / "features.db", db)
            c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            s0, t0 = steal(), time.perf_counter()
            p = subprocess.run(command(v, db), capture_output=True, text=True)
            wall, s1 = time.perf_counter() - t0, steal()
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            if p.returncode:
                print(p.stderr[-2000:], file=sys.stderr)
            vp, vi = verified_inliers(db)
            print(json.dumps(dict(scene=scene, variant=v, round=r, wall_s=round(wall, 2),
                                  cpu_s=round(c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime, 2),
                                  steal_s=round(s1 - s0, 2), rc=p.returncode, verified_pairs=vp,
                                  verified_inliers=vi, load=os.getloadavg()[0])), flush=True)


if __name__ == "__main__":
    main()
