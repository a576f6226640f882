"""Procedural meshes: closed, outward-oriented, and pre-cut parts that really are two solids."""

import numpy as np
import pytest

from ne_jax.benchmark import meshes as M


def signed_volume(mesh: M.TriMesh) -> float:
    """Divergence theorem: positive for a closed, outward-oriented mesh."""
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    return float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6.0)


@pytest.mark.parametrize("cut_z", [None, 0.3, -0.5])
def test_sphere_volume_and_orientation(cut_z):
    r = 0.8
    mesh = M.sphere(r, 96, 0.03, cut_z)
    exact = 4.0 / 3.0 * np.pi * r**3
    # Inscribed polyhedron: a little smaller; the pre-cut gap removes ~2 * CUT_GAP * disc area.
    assert signed_volume(mesh) == pytest.approx(exact, rel=3e-3)


def test_precut_cylinder_is_two_closed_pieces():
    mesh = M.cylinder(0.5, -1.0, 1.0, 64, 0.1, cut_z=0.2)
    lower = mesh.vertices[:, 2] < 0.2
    faces_lower = lower[mesh.faces].all(1)
    assert (faces_lower | (~lower[mesh.faces]).all(1)).all(), "a face spans the cut"
    exact_disc = np.pi * 0.25 * (64 / (2 * np.pi)) * np.sin(2 * np.pi / 64)  # inscribed 64-gon area
    for sel, height in ((faces_lower, 1.2 - M.CUT_GAP), (~faces_lower, 0.8 - M.CUT_GAP)):
        piece = M.TriMesh(mesh.vertices, mesh.faces[sel], mesh.material[sel])
        assert signed_volume(piece) == pytest.approx(exact_disc * height, rel=1e-9)


def test_box_volume_and_precut():
    assert signed_volume(M.box((-1, -1, -1), (1, 2, 3), 0.25)) == pytest.approx(2 * 3 * 4, rel=1e-12)
    cut = M.box((-1, -1, -1), (1, 1, 1), 0.25, cut_z=0.0)
    assert signed_volume(cut) == pytest.approx(8 - 8 * M.CUT_GAP, rel=1e-12)
    with pytest.raises(ValueError, match="cut_z=2"):
        M.box((-1, -1, -1), (1, 1, 1), 0.25, cut_z=2.0)


def test_torus_and_tube_volumes():
    major, minor = 0.8, 0.2
    exact = 2 * np.pi**2 * major * minor**2
    assert signed_volume(M.torus(major, minor, 256, 64)) == pytest.approx(exact, rel=2e-3)
    path = np.stack([np.linspace(-1, 1, 30), np.zeros(30), np.zeros(30)], 1)
    assert signed_volume(M.tube(path, 0.2, 64, closed=False)) == pytest.approx(np.pi * 0.04 * 2, rel=2e-3)


def test_mug_profile_cut_gives_annulus_cap():
    loop = [
        M.Piece(np.array([[0.0, -1.0], [1.0, -1.0]])),
        M.Piece(np.array([[1.0, -1.0], [1.0, 1.0]])),
        M.Piece(np.array([[1.0, 1.0], [0.8, 1.0]])),
        M.Piece(np.array([[0.8, 1.0], [0.8, -0.8]])),
        M.Piece(np.array([[0.8, -0.8], [0.0, -0.8]])),
        M.Piece(np.array([[0.0, -0.8], [0.0, -1.0]]), virtual=True),
    ]
    upper = M.clip_profile(loop, keep_below=False, level=0.0)
    caps = [p.points for p in upper if np.allclose(p.points[:, 1], 0.0)]
    assert len(caps) == 1 and sorted(caps[0][:, 0]) == pytest.approx([0.8, 1.0])
    lower = M.clip_profile(loop, keep_below=True, level=0.0)
    caps = [p.points for p in lower if np.allclose(p.points[:, 1], 0.0)]
    assert len(caps) == 1 and sorted(caps[0][:, 0]) == pytest.approx([0.8, 1.0])


def test_profile_crossing_four_times_is_refused():
    zigzag = np.array([[0.0, -1.0], [1.0, 1.0], [1.2, -1.0], [1.4, 1.0], [0.0, 1.0]])
    loop = [M.Piece(zigzag), M.Piece(np.array([[0.0, 1.0], [0.0, -1.0]]), virtual=True)]
    with pytest.raises(ValueError, match="crosses the cut z=0.0 4 times"):
        M.clip_profile(loop, True, 0.0)


def test_vertex_normals_unit_and_outward_on_sphere():
    mesh = M.sphere(1.0, 48, 0.05)
    n = M.vertex_normals(mesh.vertices, mesh.faces)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    away_from_poles = np.abs(mesh.vertices[:, 2]) < 0.99
    cos = np.sum(n * mesh.vertices, 1)[away_from_poles]
    assert cos.min() > 0.99


def test_sample_surface_is_on_surface_and_area_uniform():
    mesh = M.box((0, 0, 0), (1, 1, 1), 0.5)
    face, bary = M.sample_surface(mesh, 60_000, np.random.default_rng(0))
    assert np.all(bary >= 0) and np.allclose(bary.sum(1), 1)
    p = M.interpolate(mesh.vertices, mesh.faces, face, bary)
    on_face = np.isclose(p, 0) | np.isclose(p, 1)
    assert on_face.any(1).all()
    counts = [np.mean(np.isclose(p[:, k], v)) for k in range(3) for v in (0, 1)]
    assert np.allclose(counts, 1 / 6, atol=0.01)  # six equal faces, equal share
