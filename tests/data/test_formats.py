"""Format readers (COLMAP, nerfstudio, NSVF, LLFF): tiny scene folders written in each format's
own convention read back as one :class:`Capture` (OpenGL camera-to-world, pixel intrinsics,
splits, points), and bad inputs raise :class:`DataError` naming the file."""

from __future__ import annotations

import json
import shutil

import formats_fixtures as fx
import numpy as np
import pytest

from ne_jax.data.capture import Capture
from ne_jax.data.formats import READERS, colmap, llff, nerfstudio, nsvf
from ne_jax.data.formats.colmap import read_colmap
from ne_jax.data.formats.llff import read_llff
from ne_jax.data.formats.nerfstudio import read_nerfstudio
from ne_jax.data.formats.nsvf import read_nsvf
from ne_jax.data.ply import write_ply
from ne_jax.data.png import DataError

N = 10
NAMES = [f"img_{i:02d}.png" for i in range(N)]


def _assert_poses(capture: Capture, c2w_gl: np.ndarray, names: list[str]) -> None:
    got = {v.name: v.c2w for v in capture.views}
    assert sorted(got) == sorted(names)
    for name, m in zip(names, c2w_gl):
        assert got[name].dtype == np.float64 and got[name].shape == (4, 4)
        np.testing.assert_allclose(got[name], m, atol=1e-9, rtol=0)


def _every_8th(n: int) -> dict[str, tuple[int, ...]]:
    test = tuple(range(0, n, 8))
    return {"train": tuple(i for i in range(n) if i not in test), "test": test}


# ----------------------------------------------------------------------------------------------
# Registry
# ----------------------------------------------------------------------------------------------


def test_readers_in_detection_order_and_each_recognises_only_its_own(tmp_path):
    assert list(READERS) == ["nerfstudio", "colmap", "nsvf", "llff"]
    c2w = fx.circle_c2w(N)
    roots = {f: tmp_path / f for f in READERS}
    fx.write_nerfstudio(roots["nerfstudio"], c2w, [f"images/{n}" for n in NAMES])
    fx.write_colmap_text(roots["colmap"], c2w, NAMES)
    fx.write_nsvf(roots["nsvf"], c2w, [f"0_{i:04d}.png" for i in range(N)])
    fx.write_llff(roots["llff"], c2w)
    for fmt, root in roots.items():
        matches = [f for f, (looks_like, _) in READERS.items() if looks_like(root)]
        assert matches == [fmt]
        capture = READERS[fmt][1](root)
        assert capture.format == fmt and capture.num_views == N


def test_a_nerfstudio_folder_with_a_colmap_model_is_read_as_nerfstudio(tmp_path):
    c2w = fx.circle_c2w(N)
    fx.write_nerfstudio(tmp_path, c2w, [f"images/{n}" for n in NAMES])
    fx.write_colmap_text(tmp_path, c2w, NAMES, images=False)
    first = next(f for f, (looks_like, _) in READERS.items() if looks_like(tmp_path))
    assert first == "nerfstudio" and colmap.looks_like(tmp_path)


# ----------------------------------------------------------------------------------------------
# COLMAP
# ----------------------------------------------------------------------------------------------


def test_colmap_text_model_reads_poses_intrinsics_splits_and_points(tmp_path):
    c2w = fx.circle_c2w(N)
    xyz, rgb, err = fx.default_points(7)
    names = list(reversed(NAMES))  # image ids in reverse name order: views are sorted by name
    fx.write_colmap_text(tmp_path, c2w[::-1], names, points=(xyz, rgb, err))
    cap = read_colmap(tmp_path)
    assert cap.format == "colmap" and cap.root == tmp_path
    assert [v.name for v in cap.views] == NAMES
    _assert_poses(cap, c2w, NAMES)
    for v in cap.views:
        assert (v.fx, v.fy, v.cx, v.cy, v.width, v.height) == (20.0, 21.0, 8.0, 6.0, fx.W, fx.H)
        assert v.distortion is None and v.near_far is None
        assert v.image_path == (tmp_path / "images" / v.name).resolve() and v.image_path.is_file()
    assert cap.splits == _every_8th(N) and cap.split_rule == "every 8th held out"
    assert cap.points.dtype == np.float64 and cap.point_rgb.dtype == np.float32
    np.testing.assert_array_equal(cap.points, xyz)
    np.testing.assert_allclose(cap.point_rgb, rgb / 255.0, atol=1e-7)
    np.testing.assert_allclose(cap.point_error, err, atol=1e-12)
    assert cap.bbox is None
    assert cap.source[1].endswith("sparse/0/images.txt")


def test_colmap_binary_and_text_forms_of_one_model_give_identical_captures(tmp_path):
    c2w = fx.circle_c2w(N)
    cams = (
        (1, "OPENCV", fx.W, fx.H, (20.0, 21.0, 8.0, 6.0, 0.01, -0.002, 0.001, 0.0005)),
        (2, "SIMPLE_RADIAL", fx.W, fx.H, (19.0, 8.5, 6.5, 0.03)),
    )
    which = [1 + i % 2 for i in range(N)]
    text_root, bin_root = tmp_path / "text", tmp_path / "bin"
    fx.write_colmap_text(text_root, c2w, NAMES, cameras=cams, camera_of_image=which, points=fx.default_points())
    shutil.copytree(text_root, bin_root)
    fx.text_to_binary(bin_root / "sparse" / "0")
    assert (bin_root / "sparse/0/images.bin").is_file() and not (bin_root / "sparse/0/images.txt").exists()
    a, b = read_colmap(text_root), read_colmap(bin_root)
    assert b.source[0].endswith("cameras.bin")
    assert len(a.views) == len(b.views) == N
    for va, vb in zip(a.views, b.views):
        assert va.name == vb.name
        np.testing.assert_array_equal(va.c2w, vb.c2w)
        for field in ("fx", "fy", "cx", "cy", "width", "height", "distortion"):
            assert getattr(va, field) == getattr(vb, field), field
    for field in ("points", "point_rgb", "point_error"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.splits == b.splits
    _assert_poses(b, c2w, NAMES)
    assert b.views[0].distortion == (0.01, -0.002, 0.001, 0.0005)
    assert b.views[1].distortion == (0.03, 0.0, 0.0, 0.0)


def test_colmap_known_cameras_come_out_where_they_are(tmp_path):
    """Hand-written poses: a camera at (0, 0, 5) looking down at the origin is COLMAP's
    ``q = (0, 1, 0, 0)`` (180 degrees about x), ``t = (0, 0, 5)``; in OpenGL axes its
    camera-to-world is the identity rotation at (0, 0, 5). A camera at p looking at the origin
    (written through the fixture) must sit at p with its -z axis towards the origin."""
    p = np.array([3.0, -2.0, 1.5])
    w2c = np.linalg.inv(fx.gl_to_cv(fx.look_at(p)))
    q, t = fx.rotation_to_qvec(w2c[:3, :3]), w2c[:3, 3]
    d = tmp_path / "sparse" / "0"
    d.mkdir(parents=True)
    (d / "cameras.txt").write_text("1 SIMPLE_PINHOLE 16 12 20 8 6\n")
    (d / "images.txt").write_text(
        "1 0 1 0 0 0 0 5 1 a.png\n\n"
        "2 1 0 0 0 0 0 5 1 b.png\n\n"  # identity: at (0, 0, -5) looking along +z, image up = world -y
        f"3 {' '.join(repr(float(v)) for v in (*q, *t))} 1 c.png\n\n"
    )
    (d / "points3D.txt").write_text("")
    fx.write_images(tmp_path / "images", ["a.png", "b.png", "c.png"])
    cap = read_colmap(tmp_path)
    a, b, c = cap.views
    np.testing.assert_allclose(a.c2w, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(b.c2w, [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, -5], [0, 0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(c.c2w[:3, 3], p, atol=1e-9)
    np.testing.assert_allclose(-c.c2w[:3, 2], -p / np.linalg.norm(p), atol=1e-9)
    assert c.c2w[2, 1] > 0  # the image's up is the world's up (+z)
    assert (a.fx, a.fy, a.cx, a.cy) == (20.0, 20.0, 8.0, 6.0)
    assert cap.points is None and cap.point_rgb is None


@pytest.mark.parametrize(
    "model, params, expected",
    [
        ("SIMPLE_PINHOLE", (20, 8, 6), (20, 20, 8, 6, None)),
        ("PINHOLE", (20, 21, 8, 6), (20, 21, 8, 6, None)),
        ("SIMPLE_RADIAL", (20, 8, 6, 0.1), (20, 20, 8, 6, (0.1, 0.0, 0.0, 0.0))),
        ("SIMPLE_RADIAL", (20, 8, 6, 0.0), (20, 20, 8, 6, None)),
        ("RADIAL", (20, 8, 6, 0.1, -0.2), (20, 20, 8, 6, (0.1, -0.2, 0.0, 0.0))),
        ("OPENCV", (20, 21, 8, 6, 0.1, -0.2, 0.01, 0.02), (20, 21, 8, 6, (0.1, -0.2, 0.01, 0.02))),
        ("OPENCV", (20, 21, 8, 6, 0, 0, 0, 0), (20, 21, 8, 6, None)),
        (
            "FULL_OPENCV",
            (20, 21, 8, 6, 0.1, -0.2, 0.01, 0.02, 0.3, 0.4, 0.5, 0.6),
            (20, 21, 8, 6, (0.1, -0.2, 0.01, 0.02, 0.3, 0.4, 0.5, 0.6)),
        ),
    ],
)
def test_colmap_camera_models(tmp_path, model, params, expected):
    fx.write_colmap_text(tmp_path, fx.circle_c2w(3), NAMES[:3], cameras=((7, model, fx.W, fx.H, params),))
    v = read_colmap(tmp_path).views[0]
    assert (v.fx, v.fy, v.cx, v.cy, v.distortion) == expected


@pytest.mark.parametrize(
    "model, params",
    [
        ("OPENCV_FISHEYE", (20, 21, 8, 6, 0.1, 0, 0, 0)),
        ("SIMPLE_RADIAL_FISHEYE", (20, 8, 6, 0.1)),
        ("FOV", (20, 21, 8, 6, 0.5)),
    ],
)
def test_colmap_unsupported_camera_model_names_camera_and_model(tmp_path, model, params):
    cams = ((1, "PINHOLE", fx.W, fx.H, (20, 21, 8, 6)), (4, model, fx.W, fx.H, params))
    fx.write_colmap_text(tmp_path, fx.circle_c2w(4), NAMES[:4], cameras=cams, camera_of_image=[1, 1, 4, 1])
    with pytest.raises(DataError) as e:
        read_colmap(tmp_path)
    msg = str(e.value)
    assert "cameras.txt" in msg and "camera 4" in msg and model in msg
    assert "SIMPLE_PINHOLE" in msg and "FULL_OPENCV" in msg


def test_colmap_unused_fisheye_camera_is_ignored(tmp_path):
    cams = ((1, "PINHOLE", fx.W, fx.H, (20, 21, 8, 6)), (2, "OPENCV_FISHEYE", fx.W, fx.H, (20, 21, 8, 6, 0, 0, 0, 0)))
    fx.write_colmap_text(tmp_path, fx.circle_c2w(3), NAMES[:3], cameras=cams)
    assert read_colmap(tmp_path).num_views == 3


def test_colmap_fewer_than_three_registered_images(tmp_path):
    fx.write_colmap_text(tmp_path, fx.circle_c2w(2), NAMES[:2])
    with pytest.raises(DataError, match=r"images\.txt.*at least 3 registered images.*found 2"):
        read_colmap(tmp_path)


def test_colmap_only_registered_images_are_views(tmp_path):
    import pycolmap

    c2w = fx.circle_c2w(4)
    d = fx.write_colmap_text(tmp_path, c2w, NAMES[:4])
    rec = pycolmap.Reconstruction(str(d))
    dropped = next(im for im in rec.images.values() if im.name == NAMES[1])
    rec.deregister_frame(dropped.frame_id)
    shutil.rmtree(d)
    d.mkdir()
    rec.write_binary(str(d))
    cap = read_colmap(tmp_path)
    assert [v.name for v in cap.views] == [NAMES[0], NAMES[2], NAMES[3]]
    _assert_poses(cap, c2w[[0, 2, 3]], [NAMES[0], NAMES[2], NAMES[3]])


def test_colmap_nan_pose_in_binary_model(tmp_path):
    import pycolmap

    d = fx.write_colmap_text(tmp_path, fx.circle_c2w(3), NAMES[:3])
    rec = pycolmap.Reconstruction(str(d))
    im = next(im for im in rec.images.values() if im.name == NAMES[2])
    rec.frames[im.frame_id].rig_from_world = pycolmap.Rigid3d(
        pycolmap.Rotation3d(np.array([0.0, 0.0, 0.0, 1.0])), np.array([np.nan, 0.0, 0.0])
    )
    shutil.rmtree(d)
    d.mkdir()
    rec.write_binary(str(d))
    with pytest.raises(DataError, match=rf"images\.bin \[image {im.image_id} '{NAMES[2]}'\].*NaN"):
        read_colmap(tmp_path)


def test_colmap_image_missing_from_images_folder(tmp_path):
    fx.write_colmap_text(tmp_path, fx.circle_c2w(4), NAMES[:4])
    (tmp_path / "images" / NAMES[2]).unlink()
    with pytest.raises(DataError, match=rf"images\.txt \[image 3 '{NAMES[2]}'\].*{NAMES[2]}.*does not exist"):
        read_colmap(tmp_path)


def test_colmap_image_of_another_size_than_its_camera(tmp_path):
    fx.write_colmap_text(tmp_path, fx.circle_c2w(3), NAMES[:3])
    fx.write_images(tmp_path / "images", [NAMES[1]], width=8, height=6)
    with pytest.raises(DataError, match=rf"images\.txt.*{NAMES[1]}.*is 8x6.*expected 16x12"):
        read_colmap(tmp_path)


def test_colmap_model_directly_in_sparse_and_broken_models(tmp_path):
    root = tmp_path / "flat"
    fx.write_colmap_text(root, fx.circle_c2w(3), NAMES[:3], model_dir="sparse")
    assert colmap.looks_like(root) and read_colmap(root).num_views == 3
    assert not colmap.looks_like(tmp_path / "nothing")
    (root / "sparse" / "points3D.txt").unlink()
    with pytest.raises(DataError, match=r"sparse: incomplete COLMAP model.*cameras.txt"):
        read_colmap(root)
    broken = tmp_path / "broken"
    d = fx.write_colmap_text(broken, fx.circle_c2w(3), NAMES[:3])
    (d / "images.txt").write_text("1 1 0 0 0 0 0 4 1 a.png\nnot numbers\n2 x y\n")
    with pytest.raises(DataError, match=r"sparse/0: cannot read the text COLMAP model"):
        read_colmap(broken)


# ----------------------------------------------------------------------------------------------
# nerfstudio
# ----------------------------------------------------------------------------------------------


def test_nerfstudio_reads_poses_intrinsics_and_holdout_splits(tmp_path):
    c2w = fx.circle_c2w(N)
    order = np.random.default_rng(0).permutation(N)  # frames out of order: views sorted by file_path
    written = [f"./images/{NAMES[i]}" for i in order]
    fx.write_nerfstudio(tmp_path, c2w[order], written)
    cap = read_nerfstudio(tmp_path)
    assert cap.format == "nerfstudio"
    assert [v.name for v in cap.views] == [f"images/{n}" for n in NAMES]
    _assert_poses(cap, c2w, [f"images/{n}" for n in NAMES])
    for v in cap.views:
        assert (v.fx, v.fy, v.cx, v.cy, v.width, v.height, v.distortion) == (20.0, 21.0, 8.0, 6.0, fx.W, fx.H, None)
        assert v.image_path.is_file()
    assert cap.splits == _every_8th(N) and cap.split_rule == "every 8th held out"
    assert cap.points is None and cap.source == (str(tmp_path / "transforms.json"),)


def test_nerfstudio_per_frame_intrinsics_win_and_opencv_distortion(tmp_path):
    c2w = fx.circle_c2w(4)
    names = [f"images/{n}" for n in NAMES[:4]]
    glob = {
        "camera_model": "OPENCV",
        "fl_x": 20.0,
        "fl_y": 21.0,
        "cx": 8.0,
        "cy": 6.0,
        "k1": 0.1,
        "k2": -0.05,
        "p1": 0.001,
        "p2": 0.002,
    }
    extra = [{}, {"fl_x": 30.0, "cx": 7.5}, {"k3": 0.2, "k1": 0.0}, {"k4": 0.0}]
    fx.write_nerfstudio(tmp_path, c2w, names, intrinsics=glob, frame_extra=extra)  # no w, h: from the images
    v = read_nerfstudio(tmp_path).views
    assert (v[0].fx, v[0].fy, v[0].cx, v[0].cy, v[0].width, v[0].height) == (20.0, 21.0, 8.0, 6.0, fx.W, fx.H)
    assert (v[1].fx, v[1].fy, v[1].cx, v[1].cy) == (30.0, 21.0, 7.5, 6.0)
    assert v[0].distortion == (0.1, -0.05, 0.001, 0.002, 0.0)
    assert v[2].distortion == (0.0, -0.05, 0.001, 0.002, 0.2)


def test_nerfstudio_splits_from_filenames_and_points_from_ply(tmp_path):
    c2w = fx.circle_c2w(6)
    names = [f"images/{n}" for n in NAMES[:6]]
    xyz = np.random.default_rng(2).normal(size=(5, 3))
    rgb = np.random.default_rng(3).integers(0, 256, (5, 3)).astype(np.uint8)
    write_ply(
        tmp_path / "sparse_pc.ply",
        {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]},
    )
    meta = {
        "train_filenames": [f"./{n}" for n in names[:4]],
        "test_filenames": [names[5], names[4]],
        "ply_file_path": "sparse_pc.ply",
    }
    fx.write_nerfstudio(tmp_path, c2w, names, meta_extra=meta)
    cap = read_nerfstudio(tmp_path)
    assert cap.splits == {"train": (0, 1, 2, 3), "test": (4, 5)} and cap.split_rule == "format"
    np.testing.assert_array_equal(cap.points, xyz)
    np.testing.assert_allclose(cap.point_rgb, rgb / 255.0, atol=1e-7)
    assert cap.point_error is None and cap.source[1].endswith("sparse_pc.ply")


def _ns_error(tmp_path, match, c2w=None, names=None, **kw):
    c2w = fx.circle_c2w(3) if c2w is None else c2w
    names = names or [f"images/{n}" for n in NAMES[:3]]
    fx.write_nerfstudio(tmp_path, c2w, names, **kw)
    with pytest.raises(DataError, match=match):
        read_nerfstudio(tmp_path)


def test_nerfstudio_frame_naming_an_absent_image(tmp_path):
    fx.write_nerfstudio(tmp_path, fx.circle_c2w(3), [f"images/{n}" for n in NAMES[:3]])
    (tmp_path / "images" / NAMES[1]).unlink()
    with pytest.raises(DataError, match=rf"transforms\.json \[frames\[1\]\.file_path\]: image 'images/{NAMES[1]}'"):
        read_nerfstudio(tmp_path)


def test_nerfstudio_nan_pose(tmp_path):
    c2w = fx.circle_c2w(3)
    c2w[2, 0, 3] = np.nan
    _ns_error(tmp_path, r"transforms\.json \[frames\[2\]\.transform_matrix\]: expected finite numbers", c2w=c2w)


@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", "EQUIRECTANGULAR", "FISHEYE624"])
def test_nerfstudio_unsupported_camera_model(tmp_path, model):
    _ns_error(
        tmp_path,
        rf"transforms\.json \[camera_model\]: unsupported camera model '{model}'.*PINHOLE",
        meta_extra={"camera_model": model},
    )


def test_nerfstudio_missing_intrinsics(tmp_path):
    _ns_error(
        tmp_path,
        r"transforms\.json \[frames\[0\]\.fl_y\]: missing intrinsic 'fl_y'",
        intrinsics={"fl_x": 20.0, "cx": 8.0, "cy": 6.0},
    )


def test_nerfstudio_nonzero_k4_has_no_opencv_equivalent(tmp_path):
    _ns_error(
        tmp_path,
        r"transforms\.json \[frames\[0\]\.k4\]: .*expected k4 = 0, found 0\.01",
        meta_extra={"camera_model": "OPENCV", "k1": 0.1, "k4": 0.01},
    )


def test_nerfstudio_wrong_w_h_and_unknown_split_file(tmp_path):
    _ns_error(
        tmp_path / "a",
        r"transforms\.json \[w\]: image .* is 16x12 .*expected w = 32",
        intrinsics={"fl_x": 20.0, "fl_y": 20.0, "cx": 8.0, "cy": 6.0, "w": 32, "h": 12},
    )
    _ns_error(
        tmp_path / "b",
        r"transforms\.json \[test_filenames\[0\]\]: expected the file_path of a frame",
        meta_extra={"test_filenames": ["images/nope.png"]},
    )


def test_nerfstudio_malformed_json(tmp_path):
    (tmp_path / "transforms.json").write_text('{"frames": [}')
    assert nerfstudio.looks_like(tmp_path)
    with pytest.raises(DataError, match=r"transforms\.json: malformed JSON at line 1"):
        read_nerfstudio(tmp_path)


def test_nerfstudio_nan_in_json_intrinsic(tmp_path):
    fx.write_nerfstudio(tmp_path, fx.circle_c2w(3), [f"images/{n}" for n in NAMES[:3]])
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["frames"][1]["cx"] = float("nan")
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"transforms\.json \[frames\[1\]\.cx\]: expected a finite number"):
        read_nerfstudio(tmp_path)


# ----------------------------------------------------------------------------------------------
# NSVF
# ----------------------------------------------------------------------------------------------


def test_nsvf_synthetic_form_with_three_splits_and_bbox(tmp_path):
    c2w = fx.circle_c2w(9)
    names = [f"{s}_{i:04d}.png" for s, i in zip([0, 0, 0, 0, 1, 1, 2, 2, 2], range(9))]
    fx.write_nsvf(tmp_path, c2w, names, focal=20.0, cx=8.0, cy=6.0, bbox=([-1, -2, -3], [1, 2, 3.5]))
    cap = read_nsvf(tmp_path)
    assert cap.format == "nsvf" and [v.name for v in cap.views] == names
    _assert_poses(cap, c2w, names)
    for v in cap.views:
        assert (v.fx, v.fy, v.cx, v.cy, v.width, v.height, v.distortion) == (20.0, 20.0, 8.0, 6.0, fx.W, fx.H, None)
    assert cap.splits == {"train": (0, 1, 2, 3), "val": (4, 5), "test": (6, 7, 8)} and cap.split_rule == "format"
    np.testing.assert_array_equal(cap.bbox[0], [-1, -2, -3])
    np.testing.assert_array_equal(cap.bbox[1], [1, 2, 3.5])
    assert cap.points is None and cap.source[-1].endswith("bbox.txt")


def test_nsvf_tanks_and_temples_form_matrix_intrinsics_and_val_as_test(tmp_path):
    c2w = fx.circle_c2w(6)
    names = [f"{s}_{i:04d}.jpg" for s, i in zip([0, 0, 0, 0, 1, 1], range(6))]
    fx.write_nsvf(tmp_path, c2w, names, focal=(20.0, 21.0), cx=7.5, cy=6.5, matrix_form=True)
    assert nsvf.looks_like(tmp_path)
    cap = read_nsvf(tmp_path)
    _assert_poses(cap, c2w, names)
    v = cap.views[0]
    assert (v.fx, v.fy, v.cx, v.cy) == (20.0, 21.0, 7.5, 6.5)
    assert cap.splits == {"train": (0, 1, 2, 3), "test": (4, 5)} and cap.bbox is None


def test_nsvf_without_prefixes_holds_out_every_8th(tmp_path):
    names = [f"view_{i:02d}.png" for i in range(N)]
    fx.write_nsvf(tmp_path, fx.circle_c2w(N), names)
    cap = read_nsvf(tmp_path)
    assert cap.splits == _every_8th(N) and cap.split_rule == "every 8th held out"


def test_nsvf_bad_inputs(tmp_path):
    c2w = fx.circle_c2w(3)
    names = ["0_0000.png", "0_0001.png", "1_0002.png"]
    fx.write_nsvf(tmp_path / "nopose", c2w, names)
    (tmp_path / "nopose" / "pose" / "0_0001.txt").unlink()
    with pytest.raises(DataError, match=r"rgb/0_0001\.png: no pose for this image: expected .*pose/0_0001\.txt"):
        read_nsvf(tmp_path / "nopose")

    fx.write_nsvf(tmp_path / "noimage", c2w, names)
    (tmp_path / "noimage" / "rgb" / "1_0002.png").unlink()
    with pytest.raises(DataError, match=r"pose/1_0002\.txt: no image for this pose"):
        read_nsvf(tmp_path / "noimage")

    bad = c2w.copy()
    bad[1, 2, 2] = np.nan
    fx.write_nsvf(tmp_path / "nan", bad, names)
    with pytest.raises(DataError, match=r"pose/0_0001\.txt \[pose\]: expected finite numbers"):
        read_nsvf(tmp_path / "nan")

    fx.write_nsvf(tmp_path / "intr", c2w, names)
    (tmp_path / "intr" / "intrinsics.txt").write_text("20 8\n")
    with pytest.raises(DataError, match=r"intrinsics\.txt: expected 'f cx cy 0\.' .*found lines of \[2\]"):
        read_nsvf(tmp_path / "intr")

    fx.write_nsvf(tmp_path / "prefix", c2w, ["0_0000.png", "0_0001.png", "5_0002.png"])
    with pytest.raises(DataError, match=r"rgb/5_0002\.png: expected a name starting 0_"):
        read_nsvf(tmp_path / "prefix")

    fx.write_nsvf(tmp_path / "bbox", c2w, names, bbox=([1, 0, 0], [0, 1, 1]))
    with pytest.raises(DataError, match=r"bbox\.txt \[line 1\]: expected min < max"):
        read_nsvf(tmp_path / "bbox")


# ----------------------------------------------------------------------------------------------
# LLFF
# ----------------------------------------------------------------------------------------------


def test_llff_reads_poses_scaled_focal_bounds_and_splits(tmp_path):
    c2w = fx.circle_c2w(N)
    arr = fx.write_llff(tmp_path, c2w, hwf=(2 * fx.H, 2 * fx.W, 40.0), image_size=(fx.W, fx.H), ext=".jpg")
    cap = read_llff(tmp_path)
    names = [f"img_{i:03d}.jpg" for i in range(N)]
    assert cap.format == "llff" and [v.name for v in cap.views] == names
    _assert_poses(cap, c2w, names)
    for i, v in enumerate(cap.views):
        assert (v.fx, v.fy, v.cx, v.cy, v.width, v.height) == (20.0, 20.0, fx.W / 2, fx.H / 2, fx.W, fx.H)
        assert v.near_far == (arr[i, 15], arr[i, 16]) and v.distortion is None
    assert cap.splits == _every_8th(N) and cap.split_rule == "every 8th held out"
    assert cap.points is None


def test_llff_axes_are_down_right_backwards():
    """One pose by hand: LLFF columns [down, right, backwards] = [-y, x, z] of the world is the
    OpenGL camera with right = x, up = y, backwards = z, i.e. the identity rotation."""
    pose = np.array([[0.0, 1.0, 0.0, 1.0], [-1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]])
    np.testing.assert_array_equal(llff.llff_to_opengl(pose), [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])


def test_llff_image_count_mismatch(tmp_path):
    fx.write_llff(tmp_path, fx.circle_c2w(5), ext=".png")
    (tmp_path / "images" / "img_003.png").unlink()
    with pytest.raises(DataError, match=r"poses_bounds\.npy: expected one row per image: 5 rows, but 4 images"):
        read_llff(tmp_path)


def test_llff_nan_pose_and_wrong_shape_and_aspect(tmp_path):
    c2w = fx.circle_c2w(4)
    c2w[2, 1, 1] = np.nan
    fx.write_llff(tmp_path / "nan", c2w)
    with pytest.raises(DataError, match=r"poses_bounds\.npy \[row 2 \(img_002\.jpg\) pose\]: expected finite"):
        read_llff(tmp_path / "nan")

    (tmp_path / "shape").mkdir()
    np.save(tmp_path / "shape" / "poses_bounds.npy", np.zeros((4, 15)))
    with pytest.raises(DataError, match=r"poses_bounds\.npy: expected an array \[N, 17\].*found shape \(4, 15\)"):
        read_llff(tmp_path / "shape")

    fx.write_llff(tmp_path / "aspect", fx.circle_c2w(4), hwf=(fx.H, fx.W, 20.0), image_size=(fx.W, fx.W))
    with pytest.raises(DataError, match=r"poses_bounds\.npy \[row 0 \(img_000\.jpg\)\]: image img_000\.jpg is 16x16"):
        read_llff(tmp_path / "aspect")
