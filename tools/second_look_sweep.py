"""tools/second_look_sweep.py FIRST_PASS_DB LOOK_JSON...: the second look alone, with each setting, on copies of a database
that holds only the first pass (`guidedmatch colmap DB --no-second-look`); one JSON line per setting: pairs looked at,
comparisons, thread seconds, newly verified pairs, inliers gained, verified pairs after, rounds.

    python tools/second_look_sweep.py buddha_first.db "{}" "{\"min_chained\": 32}" "{\"max_rounds\": 1}"
"""
import sys, time, json, shutil, os
from guidedmatch.collection.sources import ColmapSource
from guidedmatch.collection.sinks import ColmapSink
from guidedmatch.collection.second_look import second_look
from guidedmatch.collection.config import CollectionConfig
from guidedmatch.sfm import verified_inliers
base = sys.argv[1]
out = []
for spec in sys.argv[2:]:
    look = json.loads(spec)
    tag = base.replace('_first.db','') + '_' + '_'.join(f'{k}{v}' for k,v in look.items())
    work = tag + '.db'; log = tag + '.jsonl'
    shutil.copy(base, work)
    if os.path.exists(log): os.remove(log)
    cconf = CollectionConfig(progress=False, log_path=log)
    st0 = open('/proc/stat').readline().split()
    with ColmapSink(work, geometry="ours") as sink:
        t = time.perf_counter()
        rec = second_look(ColmapSource(work), sink, cconf, look, state_path=False)
        wall = time.perf_counter() - t
    st1 = open('/proc/stat').readline().split()
    rows = [json.loads(l) for l in open(log) if l.startswith('{"event": "pair"')]
    vp, vi = verified_inliers(work)
    r = dict(look=look, wall=wall, steal_s=(int(st1[8]) - int(st0[8])) / 100, pairs=len(rows),
             comparisons=sum(x['comparisons'] for x in rows), match_s=sum(x['match_s'] for x in rows),
             verified_new=rec['verified'], inliers_gained=rec['inliers_gained'], verified_pairs=vp, verified_inliers=vi,
             rounds=[(x['pairs'], x['verified']) for x in rec['rounds']])
    print(json.dumps(r), flush=True)
