"""tools/large_second_look_ab.py WORK [ROUNDS]: 220-image collection, pycolmap SIFT extracted once (bench_large.extract), then
`guidedmatch colmap --pairs retrieval:20` (expansion on) per variant in a fresh process, alternating; verified pairs,
within/across scene, wall time, second-look line."""
import json, shutil, sys, time
from pathlib import Path
from guidedmatch.evaluation import bench_large as bl
from guidedmatch.evaluation.bench_collection import _timed
data = Path("/work/shared/data"); work = Path(sys.argv[1]); work.mkdir(parents=True, exist_ok=True)
rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 1
print("extract", {k: v for k, v in bl.extract(data, work).items() if k != "names"}, flush=True)
names = bl.image_names(data); scenes = bl.scene_of(data, names)
variants = {"default": [], "no_second_look": ["--no-second-look"]}
out = []
for r in range(rounds):
    order = list(variants) if r % 2 == 0 else list(variants)[::-1]
    for v in order:
        db = work / f"{v}.db"
        for p in work.glob(f"{v}.db*"):
            p.unlink()
        shutil.copyfile(work / "features.db", db)
        log = work / f"{v}.jsonl"
        if log.exists(): log.unlink()
        res = _timed([sys.executable, "-m", "guidedmatch.cli", "colmap", str(db), "--pairs", "retrieval:20",
                      "--no-progress", "--log", str(log), *variants[v]], log)
        d = bl.db_pairs(db)
        ver = d["verified"]
        within = {p: n for p, n in ver.items() if scenes[p[0]] == scenes[p[1]]}
        row = dict(variant=v, round=r, wall_s=res["wall_s"], cpu_s=res["cpu_s"], tried=len(d["tried"]),
                   verified=len(ver), within=len(within), across=len(ver) - len(within),
                   within_inliers=sum(within.values()),
                   look=[x for x in res["stdout_tail"] if "second look" in x])
        out.append(row)
        print(json.dumps(row), flush=True)
(work / "large_sl.json").write_text(json.dumps(out, indent=1))
