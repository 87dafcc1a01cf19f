"""Route length ×1, ×2, ×4 at the same density → time and peak-memory ratios (target: ×2 ≤ 2.2× time).

The campus city (9×8 street nodes) with an open route of 375 m, 750 m, 1500 m: same point density,
same city, only the length of the capture changes. The scenes are generated first (once, cached
under data/); then each pipeline runs in a fresh process, so its peak RSS is that run's alone.
"cpu ×" is the ratio of CPU seconds (user + system): on a shared machine it drifts less with the
load than wall time (the target is on wall time).
usage: python bench/scaling.py [base_route_m]
"""

from __future__ import annotations

import json
import subprocess
import sys

from _common import REPO

GENERATE = r"""
import sys
sys.path.insert(0, {bench!r})
from _common import scene
print(scene("campus", 0, route_length_m={base} * {scale}, route_closed=False))
"""

RUN = r"""
import json, resource, sys
sys.path.insert(0, {bench!r})
from pathlib import Path
from _common import run_pipeline, peak_rss_mb, REPO
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
root = Path({root!r})
c0 = cpu()
seconds, res = run_pipeline("dsm.yaml", root, REPO / "out" / "bench-scaling-{scale}")
print(json.dumps({{"seconds": seconds, "cpu": cpu() - c0, "rss_mb": peak_rss_mb(), "timings": res.timings}}))
"""


def _points(root: str) -> int:
    with open(f"{root}/street/cloud.ply", "rb") as fh:
        for line in fh:
            if line.startswith(b"element vertex"):
                return int(line.split()[2])
    return 0


def _child(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if out.returncode:
        sys.exit(f"child failed:\n{out.stderr[-2000:]}")
    return out.stdout.strip().splitlines()[-1]


def main(base: str = "375") -> None:
    bench = str(REPO / "bench")
    roots = {s: _child(GENERATE.format(bench=bench, base=float(base), scale=s)) for s in (1, 2, 4)}
    rows = []
    for scale, root in roots.items():
        r = json.loads(_child(RUN.format(bench=bench, root=root, scale=scale)))
        rows.append((scale, _points(root), r))
        print(f"  ×{scale}: {r['seconds']:.1f} s ({r['cpu']:.1f} s CPU), {r['rss_mb']:.0f} MB; "
              + ", ".join(f"{k} {v:.1f}" for k, v in r["timings"].items()), flush=True)
    base_r = rows[0][2]
    print(f"{'length':>7s} {'points':>10s} {'seconds':>9s} {'time ×':>7s} {'cpu ×':>6s} {'peak MB':>9s} {'mem ×':>6s}"
          "   target: ×2 length ≤ 2.2× time")
    for scale, n, r in rows:
        print(f"{'×' + str(scale):>7s} {n:10d} {r['seconds']:9.1f} {r['seconds'] / base_r['seconds']:7.2f} "
              f"{r['cpu'] / base_r['cpu']:6.2f} {r['rss_mb']:9.0f} {r['rss_mb'] / base_r['rss_mb']:6.2f}")


if __name__ == "__main__":
    main(*sys.argv[1:])
