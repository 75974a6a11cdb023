"""mkvariant.py SCENE BASE NAME JSON: copy cache/SCENE/BASE/database.db to cache/SCENE/ours@NAME, run second_look with
SecondLookConfig(**JSON) and the matcher config of BASE (ours@k=v;...), write match.json so the bench maps it."""
import sys, json, shutil, time
from pathlib import Path
from guidedmatch.collection.sources import ColmapSource
from guidedmatch.collection.sinks import ColmapSink
from guidedmatch.collection.second_look import second_look
from guidedmatch.collection.engine import CollectionConfig
from guidedmatch.sfm import verified_inliers
from guidedmatch.evaluation.bench_accuracy import copy_database
scene, base, name, look = sys.argv[1], sys.argv[2], sys.argv[3], json.loads(sys.argv[4])
cache = Path.home() / ".cache/guidedmatch/accuracy" / scene
src = cache / base.replace("+", "_")
dst = cache / ("ours@" + name)
shutil.rmtree(dst, ignore_errors=True); dst.mkdir()
copy_database(src / "database.db", dst / "database.db")
mcfg = {}
if base.startswith("ours@"):
    for kv in base[5:].split(";"):
        k, v = kv.split("=")
        mcfg[k] = {"True": True, "true": True, "False": False, "null": None, "none": None}.get(v, v)
        if isinstance(mcfg[k], str):
            mcfg[k] = float(v)
t0 = time.perf_counter()
db = dst / "database.db"
source = ColmapSource(db)
with ColmapSink(db, geometry="ours") as sink:
    rep = second_look(source, sink, CollectionConfig(progress=False, matcher=mcfg), look)
dt = time.perf_counter() - t0
base_rec = json.loads((src / "match.json").read_text())
vp, vi = verified_inliers(db)
rec = dict(method="ours@" + name, match_s=base_rec["match_s"] + dt, command=f"{base} + second look {look}",
           verified_pairs=vp, verified_inliers=vi, second_look={k: v for k, v in rep.items() if k != "rounds"})
(dst / "match.json").write_text(json.dumps(rec, indent=1))
print(rec, [ (r['pairs'], r['verified']) for r in rep['rounds']])
