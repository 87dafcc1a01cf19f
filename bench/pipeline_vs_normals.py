"""Full pipeline time ÷ one Open3D estimate_normals pass on the same cloud (target ≤ 3×).

The normals pass (KNN 20, the per-point floor) is timed right before and right after the pipeline
and the two are averaged, so a change of machine load during the run biases the ratio less. Each
scene runs in its own process; "peak MB" is the pipeline's own peak RSS (the high-water mark is
reset after the first normals pass), the number that must stay within 8 GB on `district`. The
"cpu ratio" divides CPU seconds (user + system, all threads) instead: on a shared machine it
drifts less with the load than wall time, but it charges the multi-threaded normals pass for
both cores, so it is a second reading, not the target.

usage: python bench/pipeline_vs_normals.py [preset | scene dir | scene manifest ...]   (default: campus)

A manifest (e.g. data/cities/denhaag-long/scene-nogps.yaml, the scene without street/gps.csv) runs
that variant of its folder's scene.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from _common import REPO

CHILD = r"""
import gc, json, resource, sys
sys.path.insert(0, {bench!r})
from pathlib import Path
from _common import REPO, normals_pass_seconds, run_pipeline, scene
from toolkit.io.cloud import read_points

def cpu():  # children too: the adjust step's Ceres solve runs in a child process
    return sum(r.ru_utime + r.ru_stime for r in map(resource.getrusage, (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)))

def normals_cpu(points):
    c0 = cpu()
    wall = normals_pass_seconds(points)
    return wall, cpu() - c0

def status_mb(field):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0

ref = {ref!r}
manifest = Path(ref) if Path(ref).is_file() else None
root = manifest.parent if manifest else Path(ref) if Path(ref, "scene.yaml").is_file() else scene(ref)
name = root.name + (f"/{{manifest.stem}}" if manifest else "")
pts = read_points(root / "street" / "cloud.ply")
n, (before, before_cpu) = len(pts), normals_cpu(pts)
del pts
gc.collect()
Path("/proc/self/clear_refs").write_text("5")
c0 = cpu()
seconds, res = run_pipeline("dsm.yaml", manifest or root, REPO / "out" / f"bench-pipeline-{{name.replace('/', '-')}}")
peak = status_mb("VmHWM")
pipeline_cpu = cpu() - c0
del res.results
gc.collect()
after, after_cpu = normals_cpu(read_points(root / "street" / "cloud.ply"))
print(json.dumps({{"scene": name, "points": n, "seconds": seconds, "normals": [before, after],
                  "cpu": pipeline_cpu, "normals_cpu": [before_cpu, after_cpu],
                  "peak_mb": peak, "timings": res.timings}}))
"""


def main(refs: list[str]) -> None:
    rows = []
    for ref in refs:
        ref = str(Path(ref).resolve()) if Path(ref, "scene.yaml").is_file() or Path(ref).is_file() else ref
        out = subprocess.run([sys.executable, "-c", CHILD.format(bench=str(REPO / "bench"), ref=ref)],
                             capture_output=True, text=True)
        if out.returncode:
            sys.exit(f"{ref}: child failed:\n{out.stderr[-3000:]}")
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(r)
        per_step = ", ".join(f"{k} {v:.1f}" for k, v in r["timings"].items())
        print(f"  {r['scene']}: normals {r['normals'][0]:.1f} s before, {r['normals'][1]:.1f} s after; {per_step}",
              flush=True)
    print(f"{'scene':30s} {'points':>10s} {'pipeline s':>11s} {'normals s':>10s} {'ratio':>7s} {'cpu ratio':>10s}"
          f" {'peak MB':>8s}  target: ratio ≤ 3 (district: ≤ 8192 MB)")
    for r in rows:
        normals, normals_cpu = sum(r["normals"]) / 2, sum(r["normals_cpu"]) / 2
        print(f"{r['scene']:30s} {r['points']:10d} {r['seconds']:11.1f} {normals:10.2f} "
              f"{r['seconds'] / normals:7.2f} {r['cpu'] / normals_cpu:10.2f} {r['peak_mb']:8.0f}")


if __name__ == "__main__":
    main(sys.argv[1:] or ["campus"])
