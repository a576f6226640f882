"""Procedural triangle meshes for the benchmark scenes (host-side numpy, float64).

Shapes are built from three generators: ``lathe`` (a profile in the ``(r, z)`` half-plane revolved
about a vertical axis), ``box`` and ``tube`` (a circle swept along a 3-D path). Each smooth patch has
its own vertices, so vertex normals stay sharp at creases.

Cut edits need real geometry at the cut: ``lathe`` and ``box`` accept ``cut_z`` and are then built
*pre-cut* into a lower and an upper closed piece, each capped at ``cut_z -/+ CUT_GAP``. Unedited, the
two caps sit inside the solid and are never seen; once an edit pulls the pieces apart, the caps are
the exposed cross-section.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CUT_GAP = 1e-4
"""Half the gap between the two pieces of a pre-cut part (world units)."""


@dataclass(frozen=True)
class TriMesh:
    """``vertices [V, 3]``, ``faces [F, 3]`` (counter-clockwise = outward), ``material [F]``."""

    vertices: np.ndarray
    faces: np.ndarray
    material: np.ndarray

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def with_material(self, material_id: int) -> TriMesh:
        return TriMesh(self.vertices, self.faces, np.full(self.num_faces, material_id, np.int32))

    def translated(self, offset) -> TriMesh:
        return TriMesh(self.vertices + np.asarray(offset, np.float64), self.faces, self.material)

    def rotated(self, axis, degrees: float, pivot=(0.0, 0.0, 0.0)) -> TriMesh:
        """The mesh turned by ``degrees`` about the line through ``pivot`` along ``axis`` (any length > 0)."""
        k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
        a = np.deg2rad(degrees)
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        rot = np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)
        pivot = np.asarray(pivot, np.float64)
        return TriMesh((self.vertices - pivot) @ rot.T + pivot, self.faces, self.material)


def concatenate(meshes: list[TriMesh]) -> TriMesh:
    """One mesh holding all ``meshes`` (vertex indices shifted)."""
    verts, faces, mats, base = [], [], [], 0
    for m in meshes:
        verts.append(m.vertices)
        faces.append(m.faces + base)
        mats.append(m.material)
        base += m.vertices.shape[0]
    return TriMesh(
        np.concatenate(verts).astype(np.float64),
        np.concatenate(faces).astype(np.int32),
        np.concatenate(mats).astype(np.int32),
    )


def submesh(mesh: TriMesh, face_mask: np.ndarray) -> TriMesh:
    """The faces of ``mesh`` where ``face_mask [F]`` is true, with only the vertices they use."""
    faces = mesh.faces[face_mask]
    used, inverse = np.unique(faces, return_inverse=True)
    return TriMesh(mesh.vertices[used], inverse.reshape(faces.shape).astype(np.int32), mesh.material[face_mask])


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals ``[F, 3]`` and face areas ``[F]`` (degenerate faces: normal 0)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, double_area[:, None], out=np.zeros_like(cross), where=double_area[:, None] > 0)
    return normals, 0.5 * double_area


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals ``[V, 3]``; a vertex with no area around it gets ``+z``."""
    normals, area = face_normals(vertices, faces)
    acc = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(acc, faces[:, k], normals * area[:, None])
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    fallback = np.broadcast_to([0.0, 0.0, 1.0], acc.shape)
    return np.where(norm > 0, acc / np.where(norm > 0, norm, 1.0), fallback)


def sample_surface(mesh: TriMesh, count: int, rng: np.random.Generator):
    """Area-uniform surface samples: ``(face [n], barycentric [n, 3])`` for ``n = count`` points."""
    _, area = face_normals(mesh.vertices, mesh.faces)
    face = rng.choice(mesh.num_faces, size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u, v = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - v, v)
    return face, np.stack([1.0 - u - v, u, v], axis=1)


def interpolate(values: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Barycentric interpolation of per-vertex ``values [V, D]`` at ``(face [n], bary [n, 3])``."""
    tri = faces[face]
    return sum(bary[:, k : k + 1] * values[tri[:, k]] for k in range(3))


# ----------------------------------------------------------------------------------------- lathe


@dataclass(frozen=True)
class Piece:
    """A smooth run of a lathe profile: ``points [k, 2]`` as ``(r, z)``. A ``virtual`` piece closes
    the profile loop (e.g. along the axis) but is not meshed."""

    points: np.ndarray
    virtual: bool = False


def _clip_piece(points: np.ndarray, keep_below: bool, level: float):
    """Clip a polyline to ``z <= level`` (or ``>=``). Returns ``[(run, starts_on_cut, ends_on_cut)]``."""
    sign = 1.0 if keep_below else -1.0
    inside = sign * (points[:, 1] - level) <= 0.0
    runs, current, start_cross = [], [], False
    for i in range(len(points)):
        if i > 0 and inside[i] != inside[i - 1]:
            p, q = points[i - 1], points[i]
            t = (level - p[1]) / (q[1] - p[1])
            hit = np.array([p[0] + t * (q[0] - p[0]), level])
            if inside[i]:  # entering: start a new run at the crossing
                current, start_cross = [hit], True
            else:  # leaving: close the run at the crossing
                current.append(hit)
                runs.append((np.array(current), start_cross, True))
                current = []
        if inside[i]:
            if not current:
                start_cross = False
            current.append(points[i])
    if current:
        runs.append((np.array(current), start_cross, False))
    return runs


def clip_profile(loop: list[Piece], keep_below: bool, level: float) -> list[Piece]:
    """The part of a closed profile loop on one side of ``z = level``, closed by a cap piece.

    Crossing points are paired in loop order, which is right for profiles that cross the cut line
    exactly twice (checked)."""
    runs = []
    for piece in loop:
        for pts, start_cross, end_cross in _clip_piece(piece.points, keep_below, level):
            runs.append((Piece(pts, piece.virtual), start_cross, end_cross))
    crossings = sum(s for _, s, _ in runs)
    if crossings not in (0, 1):
        raise ValueError(f"lathe profile crosses the cut z={level} {2 * crossings} times; expected 2")
    out = []
    for i, (piece, _, end_cross) in enumerate(runs):
        out.append(piece)
        nxt, next_start_cross, _ = runs[(i + 1) % len(runs)]
        if end_cross and next_start_cross:
            out.append(Piece(np.stack([piece.points[-1], nxt.points[0]])))
    return out


def _resample(points: np.ndarray, max_edge: float) -> np.ndarray:
    """Insert points so no segment of the polyline is longer than ``max_edge``."""
    out = [points[:1]]
    for p, q in zip(points[:-1], points[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / max_edge)))
        t = np.arange(1, n + 1)[:, None] / n
        out.append(p + t * (q - p))
    return np.concatenate(out)


def _revolve(points: np.ndarray, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Revolve one profile polyline about the z axis into a strip of triangles."""
    theta = 2.0 * np.pi * np.arange(segments) / segments
    r, z = points[:, 0:1], points[:, 1:2]
    verts = np.stack(
        [r * np.cos(theta), r * np.sin(theta), np.broadcast_to(z, (len(points), segments))], axis=-1
    ).reshape(-1, 3)
    k, j = np.meshgrid(np.arange(len(points) - 1), np.arange(segments), indexing="ij")
    a, a1 = k * segments + j, k * segments + (j + 1) % segments
    b, b1 = a + segments, a1 + segments
    faces = np.concatenate([np.stack([a, a1, b], -1).reshape(-1, 3), np.stack([a1, b1, b], -1).reshape(-1, 3)])
    return verts, faces


def lathe(loop: list[Piece], segments: int, max_edge: float, cut_z: float | None = None, axis_xy=(0.0, 0.0)) -> TriMesh:
    """Revolve a closed counter-clockwise ``(r, z)`` profile loop about the vertical axis at
    ``axis_xy``. With ``cut_z`` the solid is built as two capped pieces (see the module docstring)."""
    if cut_z is None:
        parts = [loop]
    else:
        parts = [clip_profile(loop, True, cut_z - CUT_GAP), clip_profile(loop, False, cut_z + CUT_GAP)]
    meshes = []
    for part in parts:
        for piece in part:
            if piece.virtual or len(piece.points) < 2:
                continue
            verts, faces = _revolve(_resample(piece.points, max_edge), segments)
            meshes.append(TriMesh(verts, faces, np.zeros(len(faces), np.int32)))
    return concatenate(meshes).translated([axis_xy[0], axis_xy[1], 0.0])


def arc(center_rz, radius: float, start: float, stop: float, count: int) -> np.ndarray:
    """``count`` points on a circular arc in the ``(r, z)`` plane, angles in radians."""
    t = np.linspace(start, stop, count)
    return np.stack([center_rz[0] + radius * np.cos(t), center_rz[1] + radius * np.sin(t)], axis=1)


def smooth_curve(points, per_span: int = 6) -> np.ndarray:
    """Points ``[(k - 1) * per_span + 1, 2]`` on the uniform Catmull-Rom curve through ``points [k, 2]``
    (a lathe profile through a few ``(r, z)`` control points; each end point is its own outer
    neighbour), ``per_span`` samples per span, both end points included."""
    p = np.asarray(points, np.float64)
    ext = np.concatenate([p[:1], p, p[-1:]])
    t = (np.arange(per_span) / per_span)[:, None]
    spans = []
    for i in range(len(p) - 1):
        p0, p1, p2, p3 = ext[i : i + 4]
        spans.append(0.5 * (2 * p1 + (p2 - p0) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
                            + (3 * p1 - p0 - 3 * p2 + p3) * t**3))
    return np.concatenate([*spans, p[-1:]])


def sphere(radius: float, segments: int, max_edge: float, cut_z: float | None = None, center=(0, 0, 0)) -> TriMesh:
    """A sphere as a lathe of a half circle (poles on the axis), optionally pre-cut."""
    half = arc((0.0, 0.0), radius, -np.pi / 2, np.pi / 2, max(8, int(np.pi * radius / max_edge)))
    half[[0, -1], 0] = 0.0
    loop = [Piece(half), Piece(np.array([[0.0, radius], [0.0, -radius]]), virtual=True)]
    cut = None if cut_z is None else cut_z - center[2]
    return lathe(loop, segments, max_edge, cut).translated(center)


def cylinder(radius: float, z0: float, z1: float, segments: int, max_edge: float, cut_z=None,
             axis_xy=(0.0, 0.0)) -> TriMesh:
    """A closed cylinder between heights ``z0 < z1`` with flat caps, optionally pre-cut."""
    loop = [
        Piece(np.array([[0.0, z0], [radius, z0]])),
        Piece(np.array([[radius, z0], [radius, z1]])),
        Piece(np.array([[radius, z1], [0.0, z1]])),
        Piece(np.array([[0.0, z1], [0.0, z0]]), virtual=True),
    ]
    return lathe(loop, segments, max_edge, cut_z, axis_xy)


# ------------------------------------------------------------------------------------------- box


def _grid_face(origin, du, dv, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A planar grid patch ``origin + s du + t dv``, ``s, t in [0, 1]``; normal along ``du x dv``."""
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    verts = origin + s.reshape(-1, 1) * du + t.reshape(-1, 1) * dv
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * (nv + 1) + j
    b, c, d = a + (nv + 1), a + (nv + 1) + 1, a + 1
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces


def box(lo, hi, max_edge: float, cut_z: float | None = None) -> TriMesh:
    """An axis-aligned closed box ``[lo, hi]`` with subdivided faces, optionally pre-cut at ``cut_z``."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if cut_z is not None:
        if not lo[2] < cut_z < hi[2]:
            raise ValueError(f"cut_z={cut_z} is outside the box's z range [{lo[2]}, {hi[2]}]")
        return concatenate([
            box(lo, [hi[0], hi[1], cut_z - CUT_GAP], max_edge),
            box([lo[0], lo[1], cut_z + CUT_GAP], hi, max_edge),
        ])
    size = hi - lo
    n = np.maximum(1, np.ceil(size / max_edge).astype(int))
    ex, ey, ez = np.diag(size)
    patches = [  # (origin, du, dv, nu, nv) with du x dv pointing outward
        (lo, ey, ex, n[1], n[0]), (lo + ez, ex, ey, n[0], n[1]),  # bottom, top
        (lo, ex, ez, n[0], n[2]), (lo + ey, ez, ex, n[2], n[0]),  # -y, +y
        (lo, ez, ey, n[2], n[1]), (lo + ex, ey, ez, n[1], n[2]),  # -x, +x
    ]
    return concatenate([TriMesh(*_grid_face(*p), np.zeros(2 * p[3] * p[4], np.int32)) for p in patches])


# ------------------------------------------------------------------------------------------ tube


def tube(path: np.ndarray, radius: float, sides: int, closed: bool) -> TriMesh:
    """A circle of ``radius`` swept along ``path [P, 3]`` (parallel-transport frames). An open tube
    gets flat end caps; a ``closed`` one joins its last ring to its first."""
    path = np.asarray(path, np.float64)
    p = len(path)
    nxt = np.roll(path, -1, 0) if closed else np.concatenate([path[1:], 2 * path[-1:] - path[-2:-1]])
    prv = np.roll(path, 1, 0) if closed else np.concatenate([2 * path[:1] - path[1:2], path[:-1]])
    tangent = nxt - prv
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    helper = np.array([0.0, 0.0, 1.0]) if abs(tangent[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    normal = np.zeros_like(path)
    normal[0] = np.cross(np.cross(tangent[0], helper), tangent[0])
    normal[0] /= np.linalg.norm(normal[0])
    for i in range(1, p):  # parallel transport
        n = normal[i - 1] - tangent[i] * np.dot(normal[i - 1], tangent[i])
        normal[i] = n / np.linalg.norm(n)
    binormal = np.cross(tangent, normal)
    theta = 2.0 * np.pi * np.arange(sides) / sides
    ring = np.cos(theta)[None, :, None] * normal[:, None] + np.sin(theta)[None, :, None] * binormal[:, None]
    verts = (path[:, None] + radius * ring).reshape(-1, 3)
    rows = p if closed else p - 1
    i, j = np.meshgrid(np.arange(rows), np.arange(sides), indexing="ij")
    a, a1 = i * sides + j, i * sides + (j + 1) % sides
    b, b1 = ((i + 1) % p) * sides + j, ((i + 1) % p) * sides + (j + 1) % sides
    faces = np.concatenate([np.stack([a, a1, b], -1).reshape(-1, 3), np.stack([a1, b1, b], -1).reshape(-1, 3)])
    meshes = [TriMesh(verts, faces, np.zeros(len(faces), np.int32))]
    if not closed:
        for end, direction in ((0, -1.0), (p - 1, 1.0)):
            center = path[end]
            rim = center + radius * ring[end]
            cap_v = np.concatenate([center[None], rim])
            k = np.arange(sides)
            fan = np.stack([np.zeros(sides, int), 1 + k, 1 + (k + 1) % sides], -1)
            if direction < 0:
                fan = fan[:, [0, 2, 1]]
            meshes.append(TriMesh(cap_v, fan, np.zeros(sides, np.int32)))
    return concatenate(meshes)


def torus(major: float, minor: float, segments: int, sides: int, center=(0, 0, 0)) -> TriMesh:
    """A torus around the z axis through ``center``."""
    t = 2.0 * np.pi * np.arange(segments) / segments
    path = np.stack([major * np.cos(t), major * np.sin(t), np.zeros_like(t)], 1)
    return tube(path, minor, sides, closed=True).translated(center)
