"""Shared helpers for benchmarks: scene generation on demand, timing, peak memory."""

from __future__ import annotations

import os
import resource
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
# the .venv's editable install points at the checkout it was made in: a bench run from a git worktree
# (and the `crossview` commands it starts) must import this checkout's code instead
os.environ["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])


def scene(preset: str, seed: int = 0, **overrides) -> Path:
    """data/bench-<preset>-<seed>[-suffix] generated once."""
    suffix = "-".join(f"{k}{v}" for k, v in sorted(overrides.items()))
    root = REPO / "data" / f"bench-{preset}-{seed}{'-' + suffix if suffix else ''}"
    if not (root / "scene.yaml").is_file():
        from toolkit.synth.generate import generate

        t0 = time.perf_counter()
        generate(preset, seed, root, **overrides)
        print(f"(generated {root.name} in {time.perf_counter() - t0:.1f} s)", flush=True)
    return root


DEN_HAAG = REPO.parent / "shared" / "data" / "raw" / "denhaag-lod2" / "DenHaag_01.city.json"


def city_scene(city: Path = DEN_HAAG, seed: int = 0) -> Path:
    """data/bench-<city>-<seed> built once from a real city model (``crossview synth --city``)."""
    root = REPO / "data" / f"bench-{city.name.split('.')[0]}-{seed}"
    if not (root / "scene.yaml").is_file():
        if not city.is_file():
            sys.exit(f"{city}: city model not found (it lives in ../shared/data/raw); pass a scene folder instead")
        from toolkit.synth.generate import generate_from_city

        t0 = time.perf_counter()
        generate_from_city(city, seed, root)
        print(f"(generated {root.name} in {time.perf_counter() - t0:.1f} s)", flush=True)
    return root


def truth_centres(path: Path) -> np.ndarray:
    """Camera centres (C,3) of truth/cameras.txt (COLMAP images.txt layout), in image-id order."""
    import numpy as np

    from toolkit.io.colmap import qvec_to_rotmat

    rows = []
    lines = [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    for ln in lines[::2]:
        v = ln.split()
        R = qvec_to_rotmat(np.array(v[1:5], float))
        rows.append((int(v[0]), -R.T @ np.array(v[5:8], float)))
    rows.sort(key=lambda r: r[0])
    return np.array([c for _, c in rows])


def kabsch_error(src, dst):
    """Per-point 3D error of the best rigid fit (Kabsch, no scale) of ``src`` onto ``dst`` (N,3): the
    bar any non-rigid registration must beat."""
    import numpy as np

    a, b = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - a).T @ (dst - b))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return np.linalg.norm((src - a) @ R.T + b - dst, axis=1)


def similarity_scale(src, dst) -> float:
    """The scale s of the best similarity src ≈ s·R·dst + t (Umeyama): for a street cloud (src) and
    its truth in metres (dst), the frame's units per metre, the route's mean scale drift included."""
    import numpy as np

    a, b = src - src.mean(0), dst - dst.mean(0)
    U, S, Vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(U @ Vt))
    return float((S[0] + S[1] + d * S[2]) / (b ** 2).sum())


def peak_rss_mb(children: bool = False) -> float:
    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return resource.getrusage(who).ru_maxrss / 1024.0


def normals_pass_seconds(points) -> float:
    """One Open3D estimate_normals (KNN 20) pass over the cloud, as given (the per-point floor)."""
    import numpy as np
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points) - np.median(points, axis=0)))
    t0 = time.perf_counter()
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    return time.perf_counter() - t0


def run_pipeline(recipe: str, scene_dir: Path, out: Path, overrides=()):
    from toolkit.runner import run_recipe

    t0 = time.perf_counter()
    res = run_recipe(REPO / "recipes" / recipe, scene=scene_dir, out=out, overwrite=True, rerun=False,
                     overrides=list(overrides))
    return time.perf_counter() - t0, res


# --- bounded bench outputs (a variant's 36 runs hold ~4 GB with their PLY copies; the disk filled twice)
def require_free_disk(folder: Path, gib: float) -> None:
    """Stop with one line when the file system of ``folder`` has less than ``gib`` GiB free (a matrix
    that fills the disk half-way leaves runs that failed for want of room, not of the code)."""
    import shutil

    folder.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(folder).free / 2**30
    if free < gib:
        sys.exit(f"only {free:.1f} GiB free under {folder} (this bench needs {gib:.0f}): "
                 "delete old data/*/out-* folders or scenes first")


def slim_run(out: Path) -> str | None:
    """The sha256 of the run's registered.laz (to compare variants byte for byte once the folder is
    gone), after deleting registered.ply: the same points as the LAZ, three quarters of the folder."""
    import hashlib

    (out / "registered.ply").unlink(missing_ok=True)
    laz = out / "registered.laz"
    if not laz.is_file():
        return None
    h = hashlib.sha256()
    with laz.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


SLIM_MARK = ".slim"      # a variant folder reduced to its metrics and logs
SLIM_KEEP = (".json", ".log", ".yaml")   # metrics.json, timings.json, transforms.json, run.log, recipe.yaml


def _slim_age(folder: Path) -> float:
    mark = folder / SLIM_MARK
    try:
        return float(mark.read_text())
    except ValueError:
        return mark.stat().st_mtime


def _slim(folder: Path) -> None:
    """Delete all but the folder's JSON, log and YAML files (and empty sub-folders); mark it slimmed."""
    age = folder.stat().st_mtime
    for f in sorted(folder.rglob("*"), reverse=True):  # files before their folders
        if f.is_file() and f.suffix not in SLIM_KEEP:
            f.unlink()
        elif f.is_dir() and not any(f.iterdir()):
            f.rmdir()
    (folder / SLIM_MARK).write_text(repr(age))


def bound_folders(folders: list[Path], keep: int, keep_slim: int = 0) -> None:
    """Keep the ``keep`` most recently modified of ``folders`` whole; of the others, the ``keep_slim``
    newest keep only their JSON, log and YAML files (metrics.json, run.log, recipe.yaml: what re-scoring
    the run status needs, bench/status_calibration.py; a few MB a matrix), the rest are deleted,
    saying so. A slimmed folder's SLIM_MARK file holds its modification time from before it was slimmed."""
    import shutil

    folders = [d for d in folders if d.is_dir()]
    slim = [d for d in folders if (d / SLIM_MARK).is_file()]
    whole = sorted((d for d in folders if d not in slim), key=lambda d: d.stat().st_mtime, reverse=True)
    for d in whole[keep:]:
        if keep_slim > 0:
            print(f"slimming {d} to its metrics and logs (the {keep} newest variants stay whole)", flush=True)
            _slim(d)
            slim.append(d)
        else:
            print(f"removing {d} (bench outputs are kept for the {keep} newest variants)", flush=True)
            shutil.rmtree(d)
    for d in sorted(slim, key=_slim_age, reverse=True)[keep_slim:]:
        print(f"removing {d} (metrics and logs are kept for the {keep_slim} newest slimmed variants)", flush=True)
        shutil.rmtree(d)
