"""A `World` turned into PyBullet bodies, in a DIRECT (headless, CPU) physics client.

The ground is one height-field body, so its class cannot come from the body id: sensors ask the
world's ground-class raster at the hit's (x, y) instead. Every other body has one class.
`label_lut[body_id]` gives a body's class id, `GROUND` for the height field and `DROP` for bodies
that sensors must ignore (the robot itself). `MEMBER` marks the robots of a fleet: they give no
points either, but the camera's depth image shows them (a member sees the others, it does not map
them).
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p

from .worlds import BOX, CYLINDER, Primitive, World, WorldObject

GROUND = -2  # label_lut value: look the class up in the ground raster
DROP = -1  # label_lut value: not part of the world (the robot); sensors drop these hits
MEMBER = -3  # label_lut value: a fleet's robot; dropped from clouds, kept in depth images
MAX_MESH_VERTICES = 60_000  # PyBullet refuses meshes above 131,072 vertices; stay well below


def transform_points(points: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (N, 3) points, as float32. einsum, not `@`: a BLAS call
    with an inner size of 3 is slow, and its threads fight other processes for the cores."""
    r = np.asarray(m[:3, :3], np.float32)
    t = np.asarray(m[:3, 3], np.float32)
    return np.einsum("ij,kj->ik", np.asarray(points, np.float32), r) + t


class BulletScene:
    """Owns one PyBullet client holding the world's bodies."""

    def __init__(self, world: World, *, gui: bool = False, gravity: float = 9.81):
        self.world = world
        self.client = p.connect(p.GUI if gui else p.DIRECT)
        self._labels: dict[int, int] = {}
        self._lut: np.ndarray | None = None
        p.setGravity(0, 0, -gravity, physicsClientId=self.client)
        self.ground_body = self._add_ground()
        self.object_bodies: list[int] = []
        for obj in world.objects:
            for body in self._add_object(obj):
                self.register(body, obj.class_id)
                self.object_bodies.append(body)

    # -- bodies and their classes ---------------------------------------------------------------

    def register(self, body: int, label: int) -> None:
        """Give `body` a class id (or GROUND / DROP)."""
        self._labels[int(body)] = int(label)
        self._lut = None

    @property
    def label_lut(self) -> np.ndarray:
        """int32 array: body id -> class id, GROUND or DROP (DROP for unknown bodies)."""
        if self._lut is None:
            lut = np.full(max(self._labels, default=0) + 1, DROP, np.int32)
            for body, label in self._labels.items():
                lut[body] = label
            self._lut = lut
        return self._lut

    def labels_of(self, bodies: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Class ids of hits on `bodies` at world `xy` (N,2); -1 where the hit must be dropped
        (nothing hit, the robot, or a fleet's robot)."""
        lut = self.label_lut
        bodies = np.asarray(bodies)
        known = (bodies >= 0) & (bodies < len(lut))
        out = np.full(len(bodies), DROP, np.int64)
        out[known] = lut[bodies[known]]
        out[out == MEMBER] = DROP
        ground = out == GROUND
        if ground.any():
            out[ground] = self.world.ground.class_at(xy[ground, 0], xy[ground, 1])
        return out

    def close(self) -> None:
        if self.client is not None and p.isConnected(self.client):
            p.disconnect(self.client)
        self.client = None

    def __enter__(self) -> BulletScene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- building ---------------------------------------------------------------------------------

    def _add_ground(self) -> int:
        g = self.world.ground
        nx, ny = g.shape
        h = g.heights
        # Bullet wants the data with x varying fastest, and centres the field between its lowest
        # and highest point, so the body goes at the middle of the extent.
        shape = p.createCollisionShape(
            p.GEOM_HEIGHTFIELD,
            meshScale=[g.resolution_m, g.resolution_m, 1.0],
            heightfieldData=h.T.ravel().tolist(),
            numHeightfieldRows=nx,
            numHeightfieldColumns=ny,
            physicsClientId=self.client,
        )
        x0, y0, x1, y1 = g.extent
        centre = [(x0 + x1) / 2, (y0 + y1) / 2, (float(h.max()) + float(h.min())) / 2]
        body = p.createMultiBody(0, shape, basePosition=centre, physicsClientId=self.client)
        # white, so the rendered grey level is the lighting; sensors colour it from the raster
        p.changeVisualShape(body, -1, rgbaColor=[1, 1, 1, 1], physicsClientId=self.client)
        p.changeDynamics(body, -1, lateralFriction=1.0, physicsClientId=self.client)
        self.register(body, GROUND)
        return body

    def _rgba(self, class_id: int) -> list[float]:
        r, g, b = (int(c) for c in self.world.classes.colour_lut[class_id])
        return [r / 255, g / 255, b / 255, 1.0]

    def _add_object(self, obj: WorldObject) -> list[int]:
        rgba = self._rgba(obj.class_id)
        if obj.voxel_centres is not None:
            return [
                self._mesh_body(v, i, rgba, concave=True)
                for v, i in _voxel_surface_chunks(obj.voxel_centres, obj.voxel_m)
            ]
        return [self._primitive_body(prim, rgba) for prim in obj.primitives]

    def _primitive_body(self, prim: Primitive, rgba: list[float]) -> int:
        """One static body per primitive, colliding as a triangle mesh and drawn with the same
        mesh. Bullet ray-tests every convex shape (box, sphere, hull) with a GJK convex cast;
        static triangle meshes take an exact ray-triangle test through their BVH instead, which
        halves the LiDAR's cost. Sharing the mesh also makes camera and LiDAR see one surface."""
        c = self.client
        verts, idx = primitive_mesh(prim)
        cs = p.createCollisionShape(
            p.GEOM_MESH,
            vertices=verts,
            indices=idx,
            flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
            physicsClientId=c,
        )
        vs = p.createVisualShape(
            p.GEOM_MESH, vertices=verts, indices=idx, rgbaColor=rgba, physicsClientId=c
        )
        orn = p.getQuaternionFromEuler([0, 0, prim.yaw])
        return p.createMultiBody(
            0, cs, vs, basePosition=list(prim.centre), baseOrientation=orn, physicsClientId=c
        )

    def _mesh_body(self, verts: np.ndarray, idx: np.ndarray, rgba, concave: bool) -> int:
        c = self.client
        v, i = verts.tolist(), idx.ravel().tolist()
        flags = p.GEOM_FORCE_CONCAVE_TRIMESH if concave else 0
        cs = p.createCollisionShape(
            p.GEOM_MESH, vertices=v, indices=i, flags=flags, physicsClientId=c
        )
        vs = p.createVisualShape(
            p.GEOM_MESH, vertices=v, indices=i, rgbaColor=rgba, physicsClientId=c
        )
        return p.createMultiBody(0, cs, vs, physicsClientId=c)


SAGITTA_M = 0.01  # how far a tessellated curved surface may sink inside the true one


def _segments(radius: float, full_turn: bool) -> int:
    """Segments so that each chord stays within SAGITTA_M of a circle of `radius`."""
    step = 2 * math.acos(max(1 - SAGITTA_M / max(radius, 1e-6), -1.0))
    n = math.ceil((2 * math.pi if full_turn else math.pi) / max(step, 1e-3))
    return max(n, 12 if full_turn else 6)


def primitive_mesh(prim: Primitive) -> tuple[list[list[float]], list[int]]:
    """Vertices and outward triangles of a primitive, in its own frame (centre, yaw)."""
    a, b, h = prim.half_extents
    if prim.shape == BOX:
        v = [[sx * a, sy * b, sz * h] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
        quads = ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3))
        idx = [i for q0, q1, q2, q3 in quads for i in (q0, q1, q2, q0, q2, q3)]
        return v, idx
    if prim.shape == CYLINDER:
        n = _segments(a, True)
        ring = [
            (a * math.cos(2 * math.pi * k / n), a * math.sin(2 * math.pi * k / n)) for k in range(n)
        ]
        v = [[x, y, z] for z in (-h, h) for x, y in ring] + [[0.0, 0.0, -h], [0.0, 0.0, h]]
        idx = []
        for k in range(n):
            k1 = (k + 1) % n
            idx += [k, k1, n + k1, k, n + k1, n + k]  # side
            idx += [2 * n, k1, k, 2 * n + 1, n + k, n + k1]  # bottom, top
        return v, idx
    r = max(a, b, h)
    return _ellipsoid_mesh(a, b, h, _segments(r, False), _segments(r, True))


def _ellipsoid_mesh(a: float, b: float, c: float, n_lat: int, n_lon: int):
    """A UV sphere scaled to the semi-axes: vertices list and triangle indices (outward)."""
    verts = [[0.0, 0.0, c]]
    for i in range(1, n_lat):
        th = math.pi * i / n_lat
        for j in range(n_lon):
            ph = 2 * math.pi * j / n_lon
            verts.append(
                [a * math.sin(th) * math.cos(ph), b * math.sin(th) * math.sin(ph), c * math.cos(th)]
            )
    verts.append([0.0, 0.0, -c])
    bottom = len(verts) - 1

    def ring(i, j):
        return 1 + (i - 1) * n_lon + (j % n_lon)

    idx = []
    for j in range(n_lon):
        idx += [0, ring(1, j), ring(1, j + 1)]
        idx += [bottom, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)]
    for i in range(1, n_lat - 1):
        for j in range(n_lon):
            a0, a1, b0, b1 = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            idx += [a0, b0, b1, a0, b1, a1]
    return verts, idx


_FACES = (  # direction, then the 4 corners of that face of a unit cube centred at 0, outward
    ((1, 0, 0), ((1, -1, -1), (1, 1, -1), (1, 1, 1), (1, -1, 1))),
    ((-1, 0, 0), ((-1, -1, -1), (-1, -1, 1), (-1, 1, 1), (-1, 1, -1))),
    ((0, 1, 0), ((-1, 1, -1), (-1, 1, 1), (1, 1, 1), (1, 1, -1))),
    ((0, -1, 0), ((-1, -1, -1), (1, -1, -1), (1, -1, 1), (-1, -1, 1))),
    ((0, 0, 1), ((-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1))),
    ((0, 0, -1), ((-1, -1, -1), (-1, 1, -1), (1, 1, -1), (1, -1, -1))),
)


def _voxel_surface_chunks(centres: np.ndarray, voxel_m: float):
    """Yield (vertices f8[V,3], triangles i4[T,3]) meshes of the voxels' outer faces, split into
    chunks that PyBullet accepts. Faces between two occupied voxels are left out."""
    q = np.floor(centres / voxel_m).astype(np.int64)
    q = np.unique(q, axis=0)
    lo = q.min(axis=0) - 1
    qq = q - lo
    dims = qq.max(axis=0) + 2
    keys = np.sort((qq[:, 0] * dims[1] + qq[:, 1]) * dims[2] + qq[:, 2])

    def occupied(cells: np.ndarray) -> np.ndarray:
        k = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        pos = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
        return keys[pos] == k

    quads = []
    for direction, corners in _FACES:
        open_side = ~occupied(qq + np.array(direction))
        cells = q[open_side]
        centre = (cells + 0.5) * voxel_m
        corner = np.array(corners, float) * (voxel_m / 2)
        quads.append(centre[:, None, :] + corner[None, :, :])
    quads = np.concatenate(quads)  # [F, 4, 3]
    # spatially coherent chunks: sort faces along x then y, cut every MAX/4 faces
    order = np.lexsort((quads[:, 0, 1], quads[:, 0, 0]))
    quads = quads[order]
    per_chunk = MAX_MESH_VERTICES // 4
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    for s in range(0, len(quads), per_chunk):
        chunk = quads[s : s + per_chunk]
        verts = chunk.reshape(-1, 3)
        base = (np.arange(len(chunk)) * 4)[:, None, None]
        yield verts, (base + tri[None]).reshape(-1, 3).astype(np.int32)
