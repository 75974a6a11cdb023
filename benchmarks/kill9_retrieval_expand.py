# usage: python benchmarks/kill9_retrieval_expand.py  (builds a small COLMAP database of two rendered scenes first)
"""kill -9 of `guidedmatch colmap DB --pairs retrieval:2` at several moments, then a rerun: same rows as uninterrupted."""
import os, shutil, signal, sqlite3, subprocess, sys, time
from pathlib import Path
base = Path("/tmp/scale/smoke2/db.db")
if not base.exists():
    from guidedmatch.testing.multiview import make_multiview, write_views
    from guidedmatch.collection.sources import images_to_database
    for s in range(2):
        write_views(make_multiview(5, (640, 480), seed=s + 10, isolated=True, spacing=1.2), base.parent / "img" / f"s{s}")
    images_to_database(base.parent / "img", base, progress=False).close()
work = Path("/tmp/scale/kill9"); shutil.rmtree(work, ignore_errors=True); work.mkdir()
env = dict(os.environ)
cmd = lambda db: [sys.executable, "-m", "guidedmatch.cli", "colmap", str(db), "--pairs", "retrieval:2",
                  "--no-progress", "--log", "none", "--workers", "0", "--expand-rounds", "3"]
def rows(db):
    con = sqlite3.connect(db)
    r = (sorted(con.execute("SELECT pair_id, rows, cols, data FROM matches")),
         sorted(con.execute("SELECT pair_id, rows, config, F, H, data FROM two_view_geometries")))
    con.close(); return r
ref = work / "ref.db"; shutil.copyfile(base, ref)
t = time.time(); subprocess.run(cmd(ref), check=True, env=env, capture_output=True); full = time.time() - t
print("uninterrupted", round(full, 1), "s,", len(rows(ref)[1]), "pairs")
ok = 0
delays = [1, 5, 10, 15, 17, 20]  # kill as soon as the database holds this many pairs
for i, d in enumerate(delays):
    db = work / f"k{i}.db"; shutil.copyfile(base, db)
    p = subprocess.Popen(cmd(db), env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    def n_pairs():
        try:
            con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=0.05)
            try:
                return con.execute("SELECT count(*) FROM two_view_geometries").fetchone()[0]
            finally:
                con.close()
        except sqlite3.Error:
            return 0
    while p.poll() is None and n_pairs() < d:
        time.sleep(0.01)
    killed = p.poll() is None
    if killed: os.kill(p.pid, signal.SIGKILL)
    p.wait()
    before = len(rows(db)[1]); npz = Path(str(db) + ".retrieval.npz").exists(); exj = Path(str(db) + ".expansion.json").exists()
    r = subprocess.run(cmd(db), env=env, capture_output=True, text=True)
    same = rows(db) == rows(ref)
    ok += same
    print(f"kill at >= {d} pairs (killed={killed}): {before} pairs in the db after the kill (retrieval cache {npz}, expansion rounds file {exj}); rerun rc={r.returncode}; same as uninterrupted: {same}")
print(f"{ok}/{len(delays)} identical")
