"""``crossview apply RUN_DIR --cloud IN [--out OUT]``: move another cloud or mesh of the run's street
frame into the scene CRS with the run's stored warp (``warp.npz``; docs/apply.md).

Clouds (PLY, LAS/LAZ, PCD) are streamed a chunk at a time and written as LAZ (``--out`` may name
.las or .ply instead); meshes (a PLY with faces, OBJ) keep their format, faces copied. The output
is written beside under a temporary name and renamed when complete: a failed apply leaves nothing.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import CrossviewError
from toolkit.export import CarrierStats, crs_comment, export_cloud, warp_mover
from toolkit.io.attributes import CHUNK_POINTS, CloudSource, open_cloud, ply_tail_offset
from toolkit.io.cloud_out import LasGrid, PlyWriter, ply_dtype
from toolkit.warp.store import StoredWarp, load_warp

CLOUD_OUT = (".laz", ".las", ".ply")
MESH_IN = (".ply", ".obj")
KNOWN_IN = (".ply", ".las", ".laz", ".pcd", ".obj")


@dataclass(frozen=True)
class Applied:
    out: Path
    count: int
    mesh: bool
    carriers: CarrierStats
    seconds: float


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "apply", help="move another cloud or mesh of the street frame with a run's warp",
        description="Apply the warp stored in a run folder (warp.npz) to a cloud (PLY, LAS/LAZ, PCD; "
                    "written as LAZ) or a mesh (PLY with faces, OBJ; same format, faces copied) "
                    "in the run's input street frame. Each point takes the carrier segment of the "
                    "nearest street point of the run.")
    p.add_argument("run_dir", type=Path, help="a run's output folder (with warp.npz)")
    p.add_argument("--cloud", type=Path, required=True, help="the cloud or mesh to move")
    p.add_argument("--out", type=Path, help="output file (default RUN_DIR/<name>.registered.laz, "
                                            "or .ply/.obj for a mesh)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--scheduler", help="Dask scheduler whose workers move the chunks, e.g. tcp://host:8786")
    p.add_argument("--workers", type=int, default=0, help="LocalCluster worker processes that move the chunks "
                   "(default 0: this process)")
    p.add_argument("-q", "--quiet", action="store_true", help="no summary line")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from toolkit.stream import use_client

    if args.workers < 0:
        raise CrossviewError(f"--workers {args.workers}: must be 0 or more")
    from toolkit.observe import ProgressObserver

    with use_client(args.scheduler, args.workers):
        done = apply_run(args.run_dir, args.cloud, args.out, args.overwrite,
                         progress=ProgressObserver(quiet=args.quiet).progress)
    if not args.quiet:
        what = "vertices" if done.mesh else "points"
        print(f"{done.out}: {done.count} {what} moved in {done.seconds:.1f} s "
              f"({done.count / max(done.seconds, 1e-9):,.0f} per s); distance to the run's street points "
              f"mean {done.carriers.mean_m:.2f} m, max {done.carriers.max_m:.2f} m")
    return 0


def apply_run(run_dir: Path, cloud: Path, out: Path | None = None, overwrite: bool = False,
              chunk_points: int = CHUNK_POINTS, progress=None) -> Applied:
    """Every check before anything is written; then the output, atomically. ``progress``: an
    observer's ``progress``, shown while a cloud is moved a chunk at a time."""
    import time

    t0 = time.perf_counter()
    run_dir, cloud, out = Path(run_dir), Path(cloud), None if out is None else Path(out)
    if not run_dir.is_dir():
        raise CrossviewError(f"{run_dir}: run folder not found")
    suffix = cloud.suffix.lower()
    if suffix not in KNOWN_IN:
        raise CrossviewError(f"{cloud}: unsupported cloud or mesh format {suffix!r} "
                             f"(use {', '.join(KNOWN_IN)})")
    stored = load_warp(run_dir)
    source = open_cloud(cloud) if suffix != ".obj" else None
    mesh = suffix == ".obj" or source.is_mesh
    out = _out_path(run_dir, cloud, out, mesh)
    if out.resolve() == cloud.resolve():
        raise CrossviewError(f"{out}: the output would replace the input")
    if out.exists() and not overwrite:
        raise CrossviewError(f"{out}: output file already exists (pass --overwrite to replace it)")
    tmp = out.parent / f".{out.stem}.partial-{os.getpid()}{out.suffix}"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        stats = _write(stored, cloud, source, tmp, mesh, chunk_points, progress)
        tmp.replace(out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return Applied(out, stats.count, mesh, stats, time.perf_counter() - t0)


def _out_path(run_dir: Path, cloud: Path, out: Path | None, mesh: bool) -> Path:
    suffix = cloud.suffix.lower()
    if out is None:
        return run_dir / f"{cloud.stem}.registered{suffix if mesh else '.laz'}"
    allowed = (suffix,) if mesh else CLOUD_OUT
    if out.suffix.lower() not in allowed:
        kind = f"a {suffix} mesh is written as {suffix}" if mesh else f"a cloud is written as {', '.join(CLOUD_OUT)}"
        raise CrossviewError(f"{out}: {kind}")
    return out


def _write(stored: StoredWarp, cloud: Path, source: CloudSource | None, tmp: Path, mesh: bool,
           chunk_points: int, progress=None) -> CarrierStats:
    from toolkit.threads import single_threaded_blas

    grid = LasGrid(stored.las_offset_m, stored.las_scale_m)
    with single_threaded_blas():
        if source is None:
            return _write_obj(stored, cloud, tmp)
        mover = warp_mover(stored.warp, source.normals)
        if mesh:
            return _write_ply_mesh(stored, source, mover, tmp, chunk_points)
        suffix = tmp.suffix.lower()
        from toolkit.stream import active_client

        return export_cloud(source, mover, stored.crs, grid, laz=tmp if suffix in (".laz", ".las") else None,
                            ply=tmp if suffix == ".ply" else None, chunk_points=chunk_points,
                            client=active_client(), progress=progress)


def _write_ply_mesh(stored: StoredWarp, source: CloudSource, mover, tmp: Path, chunk_points: int) -> CarrierStats:
    """The vertex element moved (x, y, z as double, normals turned), the other elements copied."""
    from toolkit.export import turned_values

    head = source.ply
    fields = [("x", np.dtype("f8")), ("y", np.dtype("f8")), ("z", np.dtype("f8"))]
    fields += [(n, ply_dtype(t)) for n, t in source.fields]
    tail_lines = tuple(line for el in head.elements[1:] for line in el.lines)
    comments = (*head.comments, crs_comment(stored.crs))
    total, top = 0.0, 0.0
    with PlyWriter(tmp, source.count, fields, comments, head.fmt, tail_lines) as writer:
        for chunk in source.chunks(chunk_points):
            moved = mover(chunk)
            values = turned_values(chunk, moved, source.normals, dict(source.fields))
            writer.write({"x": moved.xyz[:, 0], "y": moved.xyz[:, 1], "z": moved.xyz[:, 2], **values})
            total, top = total + float(moved.carrier_distance_m.sum()), max(top, float(moved.carrier_distance_m.max()))
        writer.copy_tail(source.path, _tail_offset(source))
    return CarrierStats(source.count, total / max(source.count, 1), top)


def _tail_offset(source: CloudSource) -> int:
    if source.ply.fmt != "ascii":
        return ply_tail_offset(source)
    with open(source.path, "rb") as fh:
        fh.seek(source.ply.data_offset)
        for _ in range(source.count):
            fh.readline()
        return fh.tell()


def _write_obj(stored: StoredWarp, cloud: Path, tmp: Path) -> CarrierStats:
    from toolkit.io.mesh import read_obj, write_obj
    from toolkit.warp.blend import PointMaps

    mesh = read_obj(cloud)
    warp = stored.warp
    maps, _, distance = warp.move(mesh.xyz)
    paired = np.where(mesh.vn_vertex >= 0, mesh.vn_vertex, 0)
    vn = PointMaps(maps.rows[paired], maps.A, maps.b, maps.origin).rotate(mesh.vn) if len(mesh.vn) else mesh.vn
    write_obj(tmp, mesh, maps.apply(mesh.xyz), vn, crs_comment(stored.crs).replace("comment ", "", 1))
    return CarrierStats(len(mesh.xyz), float(distance.mean()), float(distance.max()))

