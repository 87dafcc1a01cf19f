"""Per-stage profile of one run: seconds, share and peak memory of each stage (which one dominates).

Peak memory per stage: the kernel's high-water mark (VmHWM) is reset before each stage
(``/proc/self/clear_refs`` = 5), read after it; "rss in" is the resident size the stage started
from (what earlier stages' outputs and caches hold). The writing of the outputs (registered.ply,
report) is measured as a last row ``outputs`` (its seconds are the run's total minus the stages).
CPU seconds (user + system, all threads) are given beside wall seconds: on a shared machine they
drift less with the load. Steps run one at a time here (``overlap=False``), so each one's CPU
seconds are its own; a plain run overlaps the over-view and street steps.

Each stage's seconds are also given as a multiple of one Open3D normals pass over the same street
cloud (KNN 20, timed before and after the run and averaged: the per-point floor the speed targets
are stated in). With truth/cameras.txt, the adjusted camera centres' error (median, p95, m) is
printed too: a faster bundle adjustment must not place the cameras worse.

usage: python bench/profile_stages.py [preset | scene dir | scene.yaml] [recipe] [KEY=VALUE ...]
       (default: campus dsm.yaml; KEY=VALUE: recipe overrides as the CLI's -s)
       (a matrix scene without GPS: data/cities/<scene>/scene-nogps.yaml)
"""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path

from _common import REPO, normals_pass_seconds, scene, truth_centres

from toolkit.observe import NullObserver


def _status_mb(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _cpu() -> float:
    """User + system seconds of this process and its finished children (the adjust step's Ceres
    solve runs in a child process, ``toolkit.forked``)."""
    return sum(r.ru_utime + r.ru_stime for r in map(resource.getrusage, (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)))


def _reset_peak() -> None:
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:  # not Linux or not permitted: peaks then accumulate from the start
        pass


class MemoryObserver(NullObserver):
    """Records, per stage, the resident size at its start and its peak (VmHWM reset at each start)."""

    def __init__(self, live: bool = True) -> None:
        super().__init__()
        self.live = live
        self.rss_in: dict[str, float] = {}
        self.peak: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    def stage_start(self, step: str, stage_key: str) -> None:
        super().stage_start(step, stage_key)
        self.rss_in[step] = _status_mb("VmRSS")
        _reset_peak()
        self.cpu[step] = _cpu()

    def stage_end(self, step: str, seconds: float, output) -> None:
        super().stage_end(step, seconds, output)
        self.cpu[step] = _cpu() - self.cpu[step]
        self.peak[step] = _status_mb("VmHWM")
        _reset_peak()
        if self.live:
            print(f"  {step:10s} {seconds:8.2f} s ({self.cpu[step]:6.2f} s CPU)  rss in {self.rss_in[step]:6.0f} MB  peak {self.peak[step]:6.0f} MB",
                  flush=True)


def profile(root: Path, recipe: str, out: Path, overrides: tuple[str, ...] = ()):
    from toolkit.runner import run_recipe

    obs = MemoryObserver()
    t0, c0 = time.perf_counter(), _cpu()
    res = run_recipe(REPO / "recipes" / recipe, scene=root, out=out, overwrite=True, rerun=False, observer=obs,
                     overlap=False, overrides=list(overrides))
    seconds, cpu = time.perf_counter() - t0, _cpu() - c0
    # a timing that is not a stage (``scale``: the no-GPS street-scale check) has no CPU or memory
    # figures of its own; its CPU seconds are counted in the ``outputs`` row
    nan = float("nan")
    rows = [(step, s, obs.cpu.get(step, nan), obs.rss_in.get(step, nan), obs.peak.get(step, nan))
            for step, s in res.timings.items()]
    rows.append(("outputs", seconds - sum(res.timings.values()), cpu - sum(obs.cpu.values()),
                 _status_mb("VmRSS"), _status_mb("VmHWM")))
    return seconds, cpu, rows


def normals_seconds(root: Path) -> float:
    from toolkit.scene import load_points, load_scene

    return normals_pass_seconds(load_points(load_scene(root), "street_cloud"))


def camera_errors(root: Path, out: Path) -> tuple[float, float] | None:
    """Median and p95 (m) of the adjusted camera centres (out/sparse) against truth/cameras.txt."""
    import numpy as np

    from toolkit.io.colmap import read_model
    from toolkit.scene import load_scene

    truth = load_scene(root).files.truth_cameras
    if truth is None or not (out / "sparse").is_dir():
        return None
    adjusted = read_model(out / "sparse")
    e = np.linalg.norm(adjusted.centres[np.argsort(adjusted.image_ids)] - truth_centres(truth), axis=1)
    return float(np.median(e)), float(np.percentile(e, 95))


def main(preset: str = "campus", recipe: str = "dsm.yaml", *overrides: str) -> None:
    root = Path(preset) if Path(preset, "scene.yaml").is_file() or Path(preset).suffix == ".yaml" else scene(preset)
    name = root.name if root.is_dir() else f"{root.parent.name}/{root.name}"
    out = REPO / "out" / f"bench-profile-{name.replace('/', '-')}"
    before = normals_seconds(root)
    seconds, cpu, rows = profile(root, recipe, out, overrides)
    normals = (before + normals_seconds(root)) / 2
    # ru_maxrss only sees the high-water mark since the last reset: the run's peak is the stages' max
    print(f"{recipe} on {name}: {seconds:.1f} s total ({cpu:.1f} s CPU, {seconds / normals:.2f}x one normals pass of "
          f"{normals:.2f} s), peak RSS {max(r[4] for r in rows if r[4] == r[4]):.0f} MB (highest stage peak)")
    print(f"{'step':10s} {'seconds':>9s} {'share':>7s} {'÷ normals':>10s} {'CPU s':>8s} {'CPU share':>10s} "
          f"{'rss in MB':>10s} {'peak MB':>9s}")
    for step, s, c, rss_in, peak in sorted(rows, key=lambda r: -r[1]):
        print(f"{step:10s} {s:9.2f} {100 * s / seconds:6.1f}% {s / normals:9.2f}x {c:8.2f} {100 * c / cpu:9.1f}% "
              f"{rss_in:10.0f} {peak:9.0f}")
    errors = camera_errors(root, out)
    if errors is not None:
        print(f"adjusted camera centres vs truth: median {errors[0]:.3f} m, p95 {errors[1]:.3f} m")


if __name__ == "__main__":
    main(*sys.argv[1:])
