"""8 scenes: serial runs vs `crossview batch` on a 2-worker LocalCluster (target ≥ 1.7×).

Besides the speed-up it prints where the parallel run loses time and the most it could gain: a plain
run already overlaps its steps on the second core (the serial arm's CPU seconds ÷ its wall time), so
two workers, whose scenes run one thread each, can reach at most 2 × serial wall ÷ worker CPU seconds.
It also prints the CPU seconds of each mode (serial: this process and its children; dask: the worker
processes, reaped with the cluster) and, per stage, the seconds summed over the scenes in each mode
(a stage slower in the workers than in serial points at contention or at a stage that uses both
cores when it runs alone).

usage: python bench/batch.py [preset]   (default: tiny)
"""

from __future__ import annotations

import resource
import sys
import time

from _common import REPO, scene

from toolkit.batch import run_batch, run_one, write_summary


def _cpu(who: int) -> float:
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def _stage_sums(rows: list[dict]) -> dict[str, float]:
    sums: dict[str, float] = {}
    for r in rows:
        for k, v in r.items():
            if k.startswith("t_") and k.endswith("_s"):
                sums[k[2:-2]] = sums.get(k[2:-2], 0.0) + v
    return sums


def main(preset: str = "tiny") -> None:
    scenes = [scene(preset, seed) for seed in range(8)]
    recipe = REPO / "recipes" / "dsm.yaml"
    out = REPO / "out" / "bench-batch"
    # serial: this process and its children (each scene's Ceres solve runs in a forked child)
    t0, c0 = time.perf_counter(), _cpu(resource.RUSAGE_SELF) + _cpu(resource.RUSAGE_CHILDREN)
    serial = [run_one(str(recipe), str(s), str(out / "serial" / s.name), [], True) for s in scenes]
    t_serial = time.perf_counter() - t0
    cpu_serial = _cpu(resource.RUSAGE_SELF) + _cpu(resource.RUSAGE_CHILDREN) - c0
    write_summary(out / "serial", serial)
    t0, c0 = time.perf_counter(), _cpu(resource.RUSAGE_CHILDREN)
    rows = run_batch(recipe, scenes, out / "dask", workers=2, overwrite=True, progress=False)
    t_dask, cpu_dask = time.perf_counter() - t0, _cpu(resource.RUSAGE_CHILDREN) - c0
    ok = sum(r["status"] == "ok" for r in rows), sum(r["status"] == "ok" for r in serial)
    per_scene = sum(r["seconds"] for r in serial), sum(r["seconds"] for r in rows)
    print(f"{'stage':10s} {'serial s':>9s} {'dask s':>8s} {'ratio':>6s}   (summed over the {len(scenes)} scenes)")
    s_sums, d_sums = _stage_sums(serial), _stage_sums(rows)
    for k, v in s_sums.items():
        print(f"{k:10s} {v:9.1f} {d_sums.get(k, float('nan')):8.1f} {d_sums.get(k, float('nan')) / v:6.2f}")
    print(f"{'per scene':10s} {per_scene[0]:9.1f} {per_scene[1]:8.1f} {per_scene[1] / per_scene[0]:6.2f}"
          "   (scene wall seconds, outputs included)")
    print(f"CPU seconds: serial {cpu_serial:.1f}, dask workers {cpu_dask:.1f}")
    # a plain run already overlaps its steps on the second core, so the serial arm is not one core
    print(f"serial runs kept {cpu_serial / t_serial:.2f} cores busy on average; two workers spreading their "
          f"{cpu_dask:.1f} CPU s perfectly would reach at most {2 * t_serial / cpu_dask:.2f}×")
    print(f"{len(scenes)} {preset} scenes: serial {t_serial:.1f} s, dask 2 workers {t_dask:.1f} s, "
          f"speed-up {t_serial / t_dask:.2f}× (target ≥ 1.7×); ok {ok[1]}/{len(scenes)} serial, {ok[0]} dask")


if __name__ == "__main__":
    main(*sys.argv[1:])
