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

from tofhil.sim import embree4
from tofhil.sim.scene import Scene, SceneObject

#: Offset of secondary-ray origins along the surface normal (m): far above float32
#: rounding of hit points at room scale (~1e-7 m), far below any modelled feature.
RAY_EPSILON_M = 1e-5

#: Rays per Embree call and per worker task.
BATCH = 1 << 16


_BOX_FACES = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6],      # -z, +z
                       [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7],      # -y, +y
                       [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])     # -x, +x


def object_mesh(obj: SceneObject) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The object's triangles in its LOCAL frame: vertices [n, 3], faces [m, 3] and, for
    smooth-shaded objects (spheres), unit vertex normals [n, 3] (None: flat facets).

    Planes and boxes are built here (no trimesh import on the common bench scenes).
    """
    if obj.type in ("plane", "board"):
        w, h = obj.params["size"] if obj.type == "plane" else obj.board.size_m
        verts = np.array([[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]])
        return verts, np.array([[0, 1, 2], [0, 2, 3]]), None
    if obj.type == "box":
        half = np.asarray(obj.params["size"], dtype=np.float64) / 2
        corners = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], dtype=np.float64)
        return corners * half, _BOX_FACES.copy(), None
    import trimesh

    if obj.type == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=obj.params["subdivisions"], radius=obj.params["radius"])
        v = np.asarray(mesh.vertices, dtype=np.float64)
        return v, np.asarray(mesh.faces), v / np.linalg.norm(v, axis=1, keepdims=True)
    if obj.type == "cylinder":
        # Flat facets: caps and side share vertices, smoothing would bend the caps.
        mesh = trimesh.creation.cylinder(radius=obj.params["radius"], height=obj.params["height"],
                                         sections=obj.params["sections"])
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), None
    scale = np.broadcast_to(np.asarray(obj.params.get("scale", 1.0), dtype=np.float64), 3)
    return np.asarray(obj.mesh.vertices, dtype=np.float64) * scale, np.asarray(obj.mesh.faces), None


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of [N, 3] arrays."""
    return np.einsum("ij,ij->i", a, b)


@dataclass
class Hits:
    """Closest hits of a ray batch, compacted to the rays that hit something."""

    index: np.ndarray | None    # which rays hit (None: all of them)
    t: np.ndarray               # [M] float64 distance along the ray
    prim: np.ndarray            # [M] global triangle index
    ng: np.ndarray              # [M, 3] unit geometric normal (as wound, not yet faced)
    uv: np.ndarray | None       # [M, 2] barycentrics, for smooth shading only
    n_rays: int

    def full(self, values: np.ndarray, fill: float | int) -> np.ndarray:
        """Scatter per-hit ``values`` back to all rays (``fill`` for misses)."""
        if self.index is None:
            return values
        out = np.full(self.n_rays, fill, dtype=np.asarray(values).dtype)
        out[self.index] = values
        return out


@dataclass
class Geometry:
    """Triangle tables of a scene and its Embree scene (thread-safe for queries)."""

    embree: object
    v0: np.ndarray          # [T, 3] float64 first vertex per triangle
    normal: np.ndarray      # [T, 3] float64 unit geometric normal
    plane_c: np.ndarray     # [T] float64 plane offset: normal . x = plane_c on the triangle
    vnormal: np.ndarray | None   # [T, 3, 3] vertex normals for smooth shading, or None
    tri_object: np.ndarray  # [T] int32 object index
    n_triangles: int
    local_bounds: list[np.ndarray]   # per object [2, 3] bounds in its local frame
    world_bounds: np.ndarray         # [2, 3] bounds of all vertices in the world
    #: The same triangles in an Embree scene that compiled kernels query directly
    #: (:mod:`tofhil.sim.embree4`); None where that binding is unavailable.
    direct: object | None = None

    @classmethod
    def build(cls, scene: Scene) -> "Geometry":
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        verts, faces, objs, vnorms = [], [], [], []
        any_smooth = False
        offset = 0
        bounds = []
        for i, obj in enumerate(scene.objects):
            v_local, fc, vn_local = object_mesh(obj)
            fc = np.asarray(fc, dtype=np.int64)
            bounds.append(np.stack([v_local.min(axis=0), v_local.max(axis=0)]))
            rot, trans = obj.pose[:3, :3], obj.pose[:3, 3]
            v = v_local @ rot.T + trans
            verts.append(v)
            faces.append(fc + offset)
            offset += len(v)
            objs.append(np.full(len(fc), i, dtype=np.int32))
            if vn_local is not None:
                any_smooth = True
                vnorms.append((vn_local @ rot.T)[fc])
            else:
                fn = np.cross(v[fc[:, 1]] - v[fc[:, 0]], v[fc[:, 2]] - v[fc[:, 0]])
                fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
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
        normal = n / norm
        direct = None
        if embree4.library() is not None and len(F):
            direct = embree4.DirectScene(V.astype(np.float32), F.astype(np.int32))
        return cls(direct=direct, embree=es, v0=np.ascontiguousarray(tri[:, 0]), normal=normal,
                   plane_c=_dot(tri[:, 0], normal), vnormal=vnormal,
                   tri_object=tri_object, n_triangles=len(F), local_bounds=bounds,
                   world_bounds=np.stack([V.min(axis=0), V.max(axis=0)]))

    # ------------------------------------------------------------------ queries
    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> "Hits":
        """Closest hits of rays ``origins`` ([N, 3], or one shared point [3]) + t ``dirs`` [N, 3].

        ``t`` is re-computed in float64 against the hit triangle's plane (exact for planar
        geometry; Embree's float32 value is kept where the ray grazes the plane).
        """
        n_rays = len(dirs)
        shared = origins.ndim == 1
        o32 = np.broadcast_to(origins.astype(np.float32), (n_rays, 3)) if shared else origins
        r = self.embree.run(np.ascontiguousarray(o32, dtype=np.float32),
                            np.ascontiguousarray(dirs, dtype=np.float32), output=1)
        prim = r["primID"]
        hit = prim >= 0
        index = None if hit.all() else np.flatnonzero(hit)
        sel = (lambda a: a) if index is None else (lambda a: a[index])
        p = sel(prim).astype(np.intp)
        n = self.normal[p]
        d = sel(dirs)
        dn = _dot(d, n)
        on = n @ origins if shared else _dot(sel(origins), n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ref = (self.plane_c[p] - on) / dn
        t_emb = sel(r["tfar"]).astype(np.float64)
        ok = np.abs(t_ref - t_emb) < 1e-4 * np.maximum(1.0, t_emb)   # NaN/inf compare False
        t = np.where(ok, t_ref, t_emb)
        uv = None
        if self.vnormal is not None:
            uv = np.stack([sel(r["u"]), sel(r["v"])], axis=1).astype(np.float64)
        return Hits(index=index, t=t, prim=p, ng=n, uv=uv, n_rays=n_rays)


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
