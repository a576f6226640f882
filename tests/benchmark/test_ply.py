"""PLY point-cloud I/O: round trips, interoperability with Open3D, clear errors."""

import numpy as np
import open3d as o3d
import pytest

from ne_jax.data.ply import PlyError, read_ply, write_ply


def sample(n=50):
    rng = np.random.default_rng(0)
    return {"x": rng.random(n).astype(np.float32), "y": rng.random(n).astype(np.float32),
            "z": rng.random(n).astype(np.float32), "nx": rng.random(n).astype(np.float32),
            "ny": rng.random(n).astype(np.float32), "nz": rng.random(n).astype(np.float32),
            "red": rng.integers(0, 255, n).astype(np.uint8), "index": np.arange(n, dtype=np.int32),
            "conf": rng.random(n)}


def test_round_trip(tmp_path):
    data = sample()
    write_ply(tmp_path / "a.ply", data)
    back = read_ply(tmp_path / "a.ply")
    assert list(back) == list(data)
    for k in data:
        np.testing.assert_array_equal(back[k], data[k])
        assert back[k].dtype == data[k].dtype


def test_open3d_reads_our_files(tmp_path):
    data = sample()
    write_ply(tmp_path / "a.ply", data)
    pcd = o3d.io.read_point_cloud(str(tmp_path / "a.ply"))
    np.testing.assert_allclose(np.asarray(pcd.points), np.stack([data["x"], data["y"], data["z"]], 1), atol=1e-7)
    np.testing.assert_allclose(np.asarray(pcd.normals), np.stack([data["nx"], data["ny"], data["nz"]], 1), atol=1e-7)


def test_reads_open3d_ascii(tmp_path):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.arange(12.0).reshape(4, 3)))
    o3d.io.write_point_cloud(str(tmp_path / "b.ply"), pcd, write_ascii=True)
    back = read_ply(tmp_path / "b.ply")
    np.testing.assert_allclose(np.stack([back["x"], back["y"], back["z"]], 1), np.arange(12.0).reshape(4, 3))


def test_errors_name_the_file(tmp_path):
    with pytest.raises(PlyError, match="not found: .*missing.ply"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"hello")
    with pytest.raises(PlyError, match="junk.ply: not a PLY file"):
        read_ply(tmp_path / "junk.ply")
    write_ply(tmp_path / "t.ply", sample())
    raw = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-10])
    with pytest.raises(PlyError, match="t.ply: truncated"):
        read_ply(tmp_path / "t.ply")
    with pytest.raises(ValueError, match="property 'y' has shape"):
        write_ply(tmp_path / "bad.ply", {"x": np.zeros(3), "y": np.zeros(4)})
    assert not (tmp_path / "bad.ply").exists()
