"""NeRF Synthetic I/O: write -> read round trips, the PNG codec, intrinsics, crash-safe writes."""

from __future__ import annotations

import io
import json
import math
import os
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from ne_jax.data import png
from ne_jax.data.nerf_synthetic import DataError, load_scene, load_split, write_split
from ne_jax.data.png import read_image, write_image


@pytest.mark.parametrize("bit_depth, tol", [(8, 0.5 / 255 + 1e-7), (16, 0.5 / 65535 + 1e-7)])
def test_round_trip(make_scene, bit_depth, tol):
    scene, data = make_scene(splits=("train", "test"), n=3, h=5, w=7, bit_depth=bit_depth)
    loaded = load_scene(scene)
    assert sorted(loaded) == ["test", "train"]
    for name, (images, c2ws) in data.items():
        s = loaded[name]
        assert s.name == name and s.num_views == 3 and (s.height, s.width) == (5, 7)
        assert s.images.dtype == np.float32 and s.images.shape == (3, 5, 7, 4)
        assert np.max(np.abs(s.images - images)) <= tol
        np.testing.assert_array_equal(s.c2w, c2ws)
        assert s.c2w.dtype == np.float32
        assert s.camera_angle_x == pytest.approx(0.8, abs=0)
        assert s.file_paths == (f"./{name}/r_0", f"./{name}/r_1", f"./{name}/r_2")
        assert s.image_paths[2] == scene / name / "r_2.png"
        focal = 0.5 * 7 / math.tan(0.4)
        assert (s.fx, s.fy, s.cx, s.cy) == pytest.approx((focal, focal, 3.5, 2.5))
    # 16 bits really keep 16 bits: an 8-bit quantisation would be off by far more than 1/65535.
    if bit_depth == 16:
        assert np.max(np.abs(loaded["train"].images - data["train"][0])) < 1e-4


def test_take_keeps_the_named_views_in_order(make_scene):
    scene, data = make_scene(splits=("test",), n=3, h=5, w=7)
    s = load_split(scene, "test")
    sub = s.take([2, 0])
    assert sub.num_views == 2 and sub.file_paths == ("./test/r_2", "./test/r_0")
    np.testing.assert_array_equal(sub.images, s.images[[2, 0]])
    np.testing.assert_array_equal(sub.c2w, data["test"][1][[2, 0]])
    assert (sub.fx, sub.cy, sub.name) == (s.fx, s.cy, "test")
    for bad in ([], [3], [-1]):
        with pytest.raises(DataError, match=r"indices: expected a non-empty list of view indices in \[0, 3\)"):
            s.take(bad)


def test_png_bytes_are_real_rgba_pngs(make_scene):
    scene, data = make_scene(bit_depth=8)
    with Image.open(scene / "train" / "r_1.png") as im:
        assert im.mode == "RGBA" and im.size == (6, 4)
        expected = np.round(data["train"][0][1] * 255).astype(np.uint8)
        np.testing.assert_array_equal(np.asarray(im), expected)


def test_rgb_images_get_alpha_one(tmp_path, random_c2w, random_rgba):
    rng = np.random.default_rng(1)
    rgb = rng.random((2, 3, 4, 3)).astype(np.float32)
    write_split(tmp_path, "val", rgb, random_c2w(rng, 2), 0.5)
    s = load_split(tmp_path, "val")
    assert s.images.shape == (2, 3, 4, 4)
    np.testing.assert_array_equal(s.images[..., 3], 1.0)
    assert np.max(np.abs(s.images[..., :3] - rgb)) <= 0.5 / 255 + 1e-7


def test_load_scene_finds_present_splits_and_checks_named_ones(make_scene):
    scene, _ = make_scene(splits=("train", "val"))
    assert sorted(load_scene(scene)) == ["train", "val"]
    with pytest.raises(DataError, match="transforms_test.json"):
        load_scene(scene, splits=("train", "test"))


def test_file_path_with_or_without_png_extension(make_scene):
    scene, data = make_scene(n=2)
    path = scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta["frames"][0]["file_path"] = "./train/r_0.png"
    meta["frames"][1]["file_path"] = "train/r_1"
    path.write_text(json.dumps(meta))
    s = load_split(scene, "train")
    assert s.image_paths == (scene / "train" / "r_0.png", scene / "train" / "r_1.png")
    assert np.max(np.abs(s.images - data["train"][0])) <= 0.5 / 255 + 1e-7


def test_explicit_intrinsics_win_over_camera_angle_x(make_scene):
    scene, _ = make_scene(h=4, w=6)
    path = scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta.update(fl_x=10.0, fl_y=12.0, cx=2.0, cy=1.5, w=6, h=4)
    path.write_text(json.dumps(meta))
    s = load_split(scene, "train")
    assert (s.fx, s.fy, s.cx, s.cy) == (10.0, 12.0, 2.0, 1.5)
    cam = s.camera(0)
    assert (float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy)) == (10.0, 12.0, 2.0, 1.5)
    assert (cam.width, cam.height) == (6, 4)
    # fl_x alone: fl_y = fl_x, principal point centred.
    del meta["fl_y"], meta["cx"], meta["cy"], meta["camera_angle_x"]
    path.write_text(json.dumps(meta))
    s = load_split(scene, "train")
    assert (s.fx, s.fy, s.cx, s.cy) == (10.0, 10.0, 3.0, 2.0)
    assert s.camera_angle_x == pytest.approx(2 * math.atan(3.0 / 10.0))


def test_write_extra_fields(tmp_path, random_c2w, random_rgba):
    rng = np.random.default_rng(2)
    write_split(tmp_path, "train", random_rgba(rng, 1, 2, 2), random_c2w(rng, 1), 0.7, extra={"fl_x": 3.0})
    assert json.loads((tmp_path / "transforms_train.json").read_text())["fl_x"] == 3.0
    assert load_split(tmp_path, "train").fx == 3.0
    with pytest.raises(DataError, match="frames"):
        write_split(tmp_path, "train", random_rgba(rng, 1, 2, 2), random_c2w(rng, 1), 0.7, extra={"frames": []})


def test_rewriting_a_split_replaces_it_whole(make_scene, random_c2w, random_rgba):
    scene, _ = make_scene(n=4)
    rng = np.random.default_rng(5)
    images, c2ws = random_rgba(rng, 2, 4, 6), random_c2w(rng, 2)
    write_split(scene, "train", images, c2ws, 0.9)
    assert sorted(os.listdir(scene / "train")) == ["r_0.png", "r_1.png"]
    s = load_split(scene, "train")
    assert s.num_views == 2 and s.camera_angle_x == 0.9
    assert sorted(os.listdir(scene)) == ["train", "transforms_train.json"]


@pytest.mark.parametrize("existing", [False, True])
def test_failed_write_leaves_nothing_half_written(make_scene, tmp_path, monkeypatch, random_c2w, random_rgba, existing):
    if existing:
        scene, data = make_scene(n=3)
        before_json = (scene / "transforms_train.json").read_bytes()
        before_imgs = {p: (scene / "train" / p).read_bytes() for p in os.listdir(scene / "train")}
    else:
        scene = tmp_path / "fresh"
    calls = {"n": 0}
    real = png.encode_png

    def flaky(img, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError("disk full (simulated)")
        return real(img, *a, **k)

    monkeypatch.setattr(png, "encode_png", flaky)
    rng = np.random.default_rng(9)
    with pytest.raises(OSError, match="simulated"):
        write_split(scene, "train", random_rgba(rng, 5, 4, 6), random_c2w(rng, 5), 0.5)
    monkeypatch.undo()
    if existing:
        assert sorted(os.listdir(scene)) == ["train", "transforms_train.json"]
        assert (scene / "transforms_train.json").read_bytes() == before_json
        assert {p: (scene / "train" / p).read_bytes() for p in os.listdir(scene / "train")} == before_imgs
        np.testing.assert_array_equal(load_split(scene, "train").c2w, data["train"][1])
    else:
        assert not scene.exists() or os.listdir(scene) == []


def test_write_image_and_read_image(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.random((3, 5, 4)).astype(np.float32)
    write_image(tmp_path / "a.png", img, bit_depth=16)
    assert np.max(np.abs(read_image(tmp_path / "a.png") - img)) <= 0.5 / 65535 + 1e-7
    assert os.listdir(tmp_path) == ["a.png"]


# --- the PNG codec -------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    h=st.integers(1, 6),
    w=st.integers(1, 6),
    channels=st.integers(1, 4),
    bit_depth=st.sampled_from([8, 16]),
    filter_type=st.integers(0, 4),
    seed=st.integers(0, 2**32 - 1),
)
def test_png_codec_round_trip_all_filters(h, w, channels, bit_depth, filter_type, seed):
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    img = np.random.default_rng(seed).integers(0, np.iinfo(dtype).max + 1, (h, w, channels)).astype(dtype)
    data = png.encode_png(img, filter_type)
    out = png.decode_png(data)
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, img)
    # Independent decoder: Pillow reads 8-bit exactly and 16-bit colour as the high byte.
    with Image.open(io.BytesIO(data)) as im:
        ref = np.asarray(im)
    if bit_depth == 8:
        np.testing.assert_array_equal(ref.reshape(img.shape), img)
    elif channels in (3, 4):
        np.testing.assert_array_equal(ref, (img >> 8).astype(np.uint8))


def test_read_image_of_pillow_written_pngs(tmp_path):
    rng = np.random.default_rng(4)
    rgba = rng.integers(0, 256, (9, 11, 4)).astype(np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png", optimize=True)  # adaptive filters
    np.testing.assert_array_equal(read_image(tmp_path / "rgba.png"), rgba / np.float32(255))
    gray = rng.integers(0, 256, (9, 11)).astype(np.uint8)
    Image.fromarray(gray, "L").save(tmp_path / "gray.png")
    out = read_image(tmp_path / "gray.png")
    for c in range(3):
        np.testing.assert_array_equal(out[..., c], gray / np.float32(255))
    np.testing.assert_array_equal(out[..., 3], 1.0)
    # palette with a transparent entry
    pal = Image.fromarray(rng.integers(0, 4, (5, 6)).astype(np.uint8), "P")
    pal.putpalette([255, 0, 0, 0, 255, 0, 0, 0, 255, 255, 255, 255])
    pal.info["transparency"] = 0
    pal.save(tmp_path / "pal.png", transparency=0)
    out = read_image(tmp_path / "pal.png")
    idx = np.asarray(pal)
    np.testing.assert_array_equal(out[..., 3], (idx != 0).astype(np.float32))
    np.testing.assert_array_equal(out[idx == 1][:, :3], np.tile([0.0, 1.0, 0.0], ((idx == 1).sum(), 1)))


def test_sixteen_bit_color_key_transparency(tmp_path):
    img = np.array([[[1000, 2000, 3000], [5, 6, 7]]], np.uint16)
    data = bytearray(png.encode_png(img))
    trns = np.array([1000, 2000, 3000], ">u2").tobytes()
    chunk = len(trns).to_bytes(4, "big") + b"tRNS" + trns + (zlib.crc32(b"tRNS" + trns) & 0xFFFFFFFF).to_bytes(4, "big")
    at = 8 + 25  # after the signature and IHDR
    (tmp_path / "k.png").write_bytes(bytes(data[:at]) + chunk + bytes(data[at:]))
    out = read_image(tmp_path / "k.png")
    np.testing.assert_array_equal(out[0, :, 3], [0.0, 1.0])
    np.testing.assert_allclose(out[0, 1, :3], np.array([5, 6, 7]) / 65535, rtol=1e-6)
