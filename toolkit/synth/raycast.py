"""Batched ray casting against a labelled mesh with Open3D ``RaycastingScene``.

Open3D takes float32: the world is in local metres (hundreds to a few thousand), where float32
resolves ~0.1 mm, and hit points are rebuilt in float64 as origin + t·direction.
"""

from __future__ import annotations

import numpy as np

from toolkit.synth.mesh import TriMesh

BATCH = 2_000_000


class Caster:
    def __init__(self, mesh: TriMesh):
        from toolkit.open3d_import import open3d
        o3d = open3d()

        self._o3d = o3d
        self.mesh = mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        if len(mesh):
            self.scene.add_triangles(
                o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
            )

    def cast(self, origins: np.ndarray, dirs: np.ndarray, want_normals: bool = False):
        """t (n,) (inf on a miss), triangle index (n,) (-1 on a miss), unit normals (n,3) or None."""
        n = len(dirs)
        t = np.full(n, np.inf, np.float32)
        prim = np.full(n, -1, np.int64)
        normals = np.zeros((n, 3), np.float32) if want_normals else None
        if not len(self.mesh) or n == 0:
            return t, prim, normals
        origins = np.broadcast_to(origins, dirs.shape)
        rays = np.empty((min(n, BATCH), 6), np.float32)
        for a in range(0, n, BATCH):
            b = min(n, a + BATCH)
            rays[: b - a, :3], rays[: b - a, 3:] = origins[a:b], dirs[a:b]
            res = self.scene.cast_rays(self._o3d.core.Tensor(rays[: b - a]))
            th = res["t_hit"].numpy()
            hit = np.isfinite(th)
            t[a:b] = th
            p = res["primitive_ids"].numpy().astype(np.int64)
            prim[a:b] = np.where(hit, p, -1)
            if want_normals:
                normals[a:b] = res["primitive_normals"].numpy()
        return t, prim, normals

    def occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """True where a ray from ``origins`` along ``dirs`` hits anything."""
        t, _, _ = self.cast(origins, dirs)
        return np.isfinite(t)
