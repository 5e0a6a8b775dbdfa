"""Scene objects -> one world-space triangle soup -> an Embree (embreex) acceleration structure.

All objects go into a single Embree triangle mesh so that Embree's ``primID`` is a global
triangle index; per-triangle tables give the object, the float64 vertices and normals.
Embree works in float32; hit distances are refined in float64 against the hit triangle's
plane so that planar geometry is exact to float64 precision.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from tofhil.sim.scene import Scene, SceneObject

#: Offset of secondary-ray origins along the surface normal (m): far above float32
#: rounding of hit points at room scale (~1e-7 m), far below any modelled feature.
RAY_EPSILON_M = 1e-5

#: Rays per Embree call and per worker task.
BATCH = 1 << 16


def object_trimesh(obj: SceneObject):
    """The object's triangle mesh in its LOCAL frame and whether it is smooth-shaded."""
    import trimesh

    if obj.type == "plane":
        w, h = obj.params["size"]
        verts = np.array([[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]])
        mesh = trimesh.Trimesh(verts, np.array([[0, 1, 2], [0, 2, 3]]), process=False)
        smooth = False
    elif obj.type == "box":
        mesh = trimesh.creation.box(extents=obj.params["size"])
        smooth = False
    elif obj.type == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=obj.params["subdivisions"],
                                          radius=obj.params["radius"])
        smooth = True
    elif obj.type == "cylinder":
        mesh = trimesh.creation.cylinder(radius=obj.params["radius"], height=obj.params["height"],
                                         sections=obj.params["sections"])
        smooth = False  # caps and side share vertices; flat facets keep the caps exact
    else:
        mesh = obj.mesh.copy()
        scale = np.asarray(obj.params.get("scale", 1.0), dtype=np.float64)
        mesh.apply_transform(np.diag(np.append(np.broadcast_to(scale, 3), 1.0)))
        smooth = False
    return mesh, smooth


@dataclass
class Geometry:
    """Triangle tables of a scene and its Embree scene (thread-safe for queries)."""

    embree: object
    v0: np.ndarray          # [T, 3] float64 first vertex per triangle
    normal: np.ndarray      # [T, 3] float64 unit geometric normal
    vnormal: np.ndarray | None   # [T, 3, 3] vertex normals for smooth shading, or None
    tri_object: np.ndarray  # [T] int32 object index
    n_triangles: int
    local_bounds: list[np.ndarray]   # per object [2, 3] bounds in its local frame
    world_bounds: np.ndarray         # [2, 3] bounds of all vertices in the world

    @classmethod
    def build(cls, scene: Scene) -> "Geometry":
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        verts, faces, objs, vnorms = [], [], [], []
        any_smooth = False
        offset = 0
        bounds = []
        for i, obj in enumerate(scene.objects):
            mesh, smooth = object_trimesh(obj)
            bounds.append(np.asarray(mesh.bounds, dtype=np.float64))
            mesh = mesh.copy()
            mesh.apply_transform(obj.pose)
            v = np.asarray(mesh.vertices, dtype=np.float64)
            fc = np.asarray(mesh.faces, dtype=np.int64)
            verts.append(v)
            faces.append(fc + offset)
            offset += len(v)
            objs.append(np.full(len(fc), i, dtype=np.int32))
            fn = np.asarray(mesh.face_normals, dtype=np.float64)
            if smooth:
                any_smooth = True
                vnorms.append(np.asarray(mesh.vertex_normals, dtype=np.float64)[fc])
            else:
                vnorms.append(np.repeat(fn[:, None, :], 3, axis=1))
        V = np.concatenate(verts)
        F = np.concatenate(faces)
        tri = V[F]                                  # [T, 3, 3]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        keep = norm[:, 0] > 0                       # drop degenerate triangles
        tri, n, norm, F = tri[keep], n[keep], norm[keep], F[keep]
        tri_object = np.concatenate(objs)[keep]
        vnormal = np.concatenate(vnorms)[keep] if any_smooth else None
        es = rtcs.EmbreeScene()
        TriangleMesh(es, V.astype(np.float32), F.astype(np.int32))
        return cls(embree=es, v0=np.ascontiguousarray(tri[:, 0]), normal=n / norm, vnormal=vnormal,
                   tri_object=tri_object, n_triangles=len(F), local_bounds=bounds,
                   world_bounds=np.stack([V.min(axis=0), V.max(axis=0)]))

    # ------------------------------------------------------------------ queries
    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest hits: (t float64 [N] (inf = miss), triangle index [N] (-1 = miss), barycentric uv [N, 2]).

        ``t`` is re-computed in float64 against the hit triangle's plane.
        """
        r = self.embree.run(np.ascontiguousarray(origins, dtype=np.float32),
                            np.ascontiguousarray(dirs, dtype=np.float32), output=1)
        prim = r["primID"].astype(np.int64)
        hit = prim >= 0
        t = np.full(len(prim), np.inf)
        p = prim[hit]
        n = self.normal[p]
        denom = np.einsum("ij,ij->i", dirs[hit], n)
        t_ref = np.einsum("ij,ij->i", self.v0[p] - origins[hit], n) / denom
        t_emb = r["tfar"][hit].astype(np.float64)
        # Refinement is exact for the hit plane; keep Embree's value where the ray grazes it.
        ok = np.isfinite(t_ref) & (np.abs(t_ref - t_emb) < 1e-4 * np.maximum(1.0, t_emb))
        t[hit] = np.where(ok, t_ref, t_emb)
        uv = np.stack([r["u"], r["v"]], axis=1).astype(np.float64)
        prim[~hit] = -1
        return t, prim, uv

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """True where something lies on the segment origin + t dir, 0 < t < dist."""
        r = self.embree.run(np.ascontiguousarray(origins, dtype=np.float32),
                            np.ascontiguousarray(dirs, dtype=np.float32),
                            dists=np.ascontiguousarray(dist, dtype=np.float32), query="OCCLUDED")
        return r >= 0

    def shading_normal(self, prim: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Unit normal at the hits (vertex-normal interpolation for smooth objects)."""
        if self.vnormal is None:
            return self.normal[prim]
        vn = self.vnormal[prim]
        u, v = uv[:, 0:1], uv[:, 1:2]
        n = (1 - u - v) * vn[:, 0] + u * vn[:, 1] + v * vn[:, 2]
        return n / np.linalg.norm(n, axis=1, keepdims=True)


class WorkerPool:
    """A small thread pool: embreex and large numpy operations release the GIL."""

    _lock = threading.Lock()
    _pool: ThreadPoolExecutor | None = None

    @classmethod
    def get(cls, threads: int) -> ThreadPoolExecutor:
        with cls._lock:
            if cls._pool is None or cls._pool._max_workers != threads:  # noqa: SLF001
                cls._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="tofhil-render")
            return cls._pool
