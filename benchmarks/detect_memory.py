"""Peak memory of feature detection vs image size (the memory guard of ``features.detect``).

Each (detector, size) runs in a fresh process: a photo is resized (INTER_AREA) to the size, the peak-RSS counter
(VmHWM) is reset through /proc/self/clear_refs, ``detectAndCompute`` runs, and the peak minus the resident size
before detection is recorded. Writes benchmarks/results/detect_memory.json (with run metadata), a Markdown table on
stdout and benchmarks/results/detect_memory.png; compare with ``features.estimate_detect_memory``.

    PYTHONPATH=src python benchmarks/detect_memory.py [--sizes 1000x750 2000x1500 3200x2400]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHILD = r'''
import json, sys, time
import cv2
from guidedmatch.datasets import data_root, list_photos
from guidedmatch.features import _make_detector
method, w, h = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
src = cv2.imread(str(list_photos(data_root())[9]), cv2.IMREAD_GRAYSCALE)
img = cv2.resize(src, (w, h), interpolation=cv2.INTER_AREA)
del src
det = _make_detector(method, None, {})
base = int(open("/proc/self/statm").read().split()[1]) * 4096
open("/proc/self/clear_refs", "w").write("5")  # reset VmHWM
t = time.perf_counter()
kps, desc = det.detectAndCompute(img, None)
dt = time.perf_counter() - t
peak = int([l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1]) * 1024
print(json.dumps(dict(method=method, w=w, h=h, pixels=w * h, extra_bytes=peak - base, features=len(kps),
                      detect_s=dt, bytes_per_pixel=(peak - base) / (w * h))))
'''


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["1000x750", "2000x1500", "3200x2400"])
    ap.add_argument("--methods", nargs="+", default=["sift", "orb", "akaze", "brisk"])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "detect_memory.json"))
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT / "src"))
    from guidedmatch.evaluation.meta import run_metadata, write_json
    from guidedmatch.features import estimate_detect_memory

    rows = []
    for m in args.methods:
        for s in args.sizes:
            w, h = (int(v) for v in s.split("x"))
            out = subprocess.run([sys.executable, "-c", CHILD, m, str(w), str(h)], capture_output=True, text=True,
                                 check=True, env={"PYTHONPATH": str(ROOT / "src"), "PATH": "/usr/bin:/bin",
                                                  "GUIDEDMATCH_DATA": __import__("os").environ.get("GUIDEDMATCH_DATA", "")})
            r = json.loads(out.stdout.strip().splitlines()[-1])
            r["estimate_bytes"] = estimate_detect_memory(w, h, m)
            rows.append(r)
            print(json.dumps(r), file=sys.stderr)
    write_json(args.out, dict(meta=run_metadata(), command=sys.argv, rows=rows))
    print("| detector | size | features | peak extra (MB) | B/px | estimate (MB) |\n|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['method']} | {r['w']}x{r['h']} | {r['features']} | {r['extra_bytes'] / 1e6:.0f} | "
              f"{r['bytes_per_pixel']:.0f} | {r['estimate_bytes'] / 1e6:.0f} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for m in args.methods:
        rr = [r for r in rows if r["method"] == m]
        line, = ax.plot([r["pixels"] / 1e6 for r in rr], [r["extra_bytes"] / 1e9 for r in rr], "o-", label=f"{m} measured")
        ax.plot([r["pixels"] / 1e6 for r in rr], [r["estimate_bytes"] / 1e9 for r in rr], "--", color=line.get_color(),
                label=f"{m} estimate")
    ax.set_xlabel("image size (Mpx)")
    ax.set_ylabel("peak extra memory (GB)")
    ax.set_title("detectAndCompute peak memory vs image size")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(Path(args.out).with_suffix(".png"), dpi=110)


if __name__ == "__main__":
    main()
