"""Every bad input raises DataError naming the file (and field / frame), the expectation and the
value found."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest

from ne_jax.data import png
from ne_jax.data.nerf_synthetic import DataError, load_scene, load_split, write_split
from ne_jax.data.png import read_image


def _raises(match_parts, fn, *args, **kwargs):
    """Assert ``fn`` raises DataError whose message contains every string of ``match_parts``."""
    with pytest.raises(DataError) as info:
        fn(*args, **kwargs)
    msg = str(info.value)
    for part in match_parts:
        assert str(part) in msg, f"{part!r} not in {msg!r}"
    return msg


def _edit_json(scene, fn, split="train"):
    path = scene / f"transforms_{split}.json"
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))
    return path


def test_is_a_value_error():
    assert issubclass(DataError, ValueError)


def test_missing_scene_dir(tmp_path):
    _raises([tmp_path / "nope", "scene directory does not exist"], load_split, tmp_path / "nope", "train")
    _raises([tmp_path / "nope", "does not exist"], load_scene, tmp_path / "nope")


def test_missing_transforms_file(make_scene):
    scene, _ = make_scene()
    _raises([scene / "transforms_val.json", "does not exist"], load_split, scene, "val")
    empty = scene / "train"  # a directory without any transforms file
    _raises([empty, "transforms_train.json"], load_scene, empty)


def test_malformed_json(make_scene):
    scene, _ = make_scene()
    path = scene / "transforms_train.json"
    path.write_text('{"camera_angle_x": 0.5,\n "frames": [}')
    _raises([path, "malformed JSON", "line 2"], load_split, scene, "train")
    path.write_text("[1, 2]")
    _raises([path, "JSON object", "list"], load_split, scene, "train")


@pytest.mark.parametrize(
    "key, where",
    [
        ("camera_angle_x", "[camera_angle_x]"),
        ("frames", "[frames]"),
    ],
)
def test_missing_top_level_key(make_scene, key, where):
    scene, _ = make_scene()
    path = _edit_json(scene, lambda m: m.pop(key))
    _raises([path, where, "missing key"], load_split, scene, "train")


@pytest.mark.parametrize("key", ["transform_matrix", "file_path"])
def test_missing_frame_key(make_scene, key):
    scene, _ = make_scene()
    path = _edit_json(scene, lambda m: m["frames"][1].pop(key))
    _raises([path, f"[frames[1].{key}]", "missing key"], load_split, scene, "train")


def test_bad_frames_values(make_scene):
    scene, _ = make_scene()
    path = _edit_json(scene, lambda m: m.update(frames=[]))
    _raises([path, "[frames]", "non-empty list"], load_split, scene, "train")
    path = _edit_json(scene, lambda m: m.update(frames=["./train/r_0"]))
    _raises([path, "[frames[0]]", "expected an object", "str"], load_split, scene, "train")
    path = _edit_json(scene, lambda m: m.update(frames=[{"file_path": 3, "transform_matrix": np.eye(4).tolist()}]))
    _raises([path, "[frames[0].file_path]", "non-empty string", "3"], load_split, scene, "train")


def test_images_of_different_sizes(make_scene):
    scene, _ = make_scene(n=3, h=4, w=6)
    png.write_image(scene / "train" / "r_2.png", np.zeros((5, 6, 4), np.float32))
    _raises(
        [scene / "transforms_train.json", "[frames[2].file_path]", "different sizes", scene / "train" / "r_2.png",
         "6x5", "6x4"],
        load_split,
        scene,
        "train",
    )


@pytest.mark.parametrize(
    "matrix, words",
    [
        (np.eye(4)[:3].tolist(), ["4x4", "(3, 4)"]),
        ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], ["4x4", "(3, 3)"]),
        ([[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]], ["4x4 array of numbers"]),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], ["last row [0, 0, 0, 1]", "[0.0, 0.0, 1.0, 1.0]"]),
        ((np.diag([2.0, 2.0, 2.0, 1.0])).tolist(), ["not orthonormal", "column lengths [2.0, 2.0, 2.0]"]),
        ([[1, 0.01, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], ["not orthonormal", "0.01"]),
        ((np.diag([1.0, 1.0, -1.0, 1.0])).tolist(), ["det < 0", "reflection"]),
        ("eye", ["4x4"]),
    ],
)
def test_transform_not_rigid_4x4(make_scene, matrix, words):
    scene, _ = make_scene()
    path = _edit_json(scene, lambda m: m["frames"][1].update(transform_matrix=matrix))
    _raises([path, "[frames[1].transform_matrix]", *words], load_split, scene, "train")


def test_transform_within_tolerance_is_accepted(make_scene):
    scene, _ = make_scene()
    m = np.eye(4)
    m[0, 1] = 4e-4  # |R^T R - I| ~ 4e-4 < 1e-3: float noise of an exporter
    _edit_json(scene, lambda meta: meta["frames"][0].update(transform_matrix=m.tolist()))
    assert load_split(scene, "train").c2w[0, 0, 1] == np.float32(4e-4)


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_nan_inf_in_transform(make_scene, token):
    scene, _ = make_scene()
    path = scene / "transforms_train.json"
    text = json.dumps(json.loads(path.read_text()))
    # replace the first translation entry of frame 0 by a non-finite JSON token
    meta = json.loads(text)
    meta["frames"][0]["transform_matrix"][0][3] = "__BAD__"
    path.write_text(json.dumps(meta).replace('"__BAD__"', token))
    _raises([path, "[frames[0].transform_matrix]", "NaN/Inf", "(0, 3)"], load_split, scene, "train")


@pytest.mark.parametrize("key", ["camera_angle_x", "fl_x", "fl_y", "cx", "cy"])
def test_nan_inf_in_intrinsics(make_scene, key):
    scene, _ = make_scene()
    path = scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    if key != "camera_angle_x":
        meta["fl_x"] = 5.0  # the other intrinsics are read only when fl_x is present
    meta[key] = "__BAD__"
    path.write_text(json.dumps(meta).replace('"__BAD__"', "NaN"))
    _raises([path, f"[{key}]", "finite number", "nan"], load_split, scene, "train")


def test_bad_intrinsic_values(make_scene):
    scene, _ = make_scene(h=4, w=6)
    path = _edit_json(scene, lambda m: m.update(camera_angle_x=4.0))
    _raises([path, "[camera_angle_x]", "(0, pi)", "4.0"], load_split, scene, "train")
    path = _edit_json(scene, lambda m: m.update(camera_angle_x="wide"))
    _raises([path, "[camera_angle_x]", "expected a number", "'wide'"], load_split, scene, "train")
    path = _edit_json(scene, lambda m: m.update(camera_angle_x=0.5, w=8))
    _raises([path, "[w]", "width 6", "8"], load_split, scene, "train")
    path = _edit_json(scene, lambda m: (m.pop("w"), m.update(fl_x=-3.0)))
    _raises([path, "[fl_x]", "positive", "-3.0"], load_split, scene, "train")


def test_frame_points_at_missing_image(make_scene):
    scene, _ = make_scene()
    (scene / "train" / "r_1.png").unlink()
    _raises(
        [scene / "transforms_train.json", "[frames[1].file_path]", "'./train/r_1'", "does not exist",
         scene / "train" / "r_1.png"],
        load_split,
        scene,
        "train",
    )
    path = _edit_json(scene, lambda m: m["frames"][0].update(file_path="./train/r_0.jpg"))
    _raises([path, "[frames[0].file_path]", "r_0.jpg"], load_split, scene, "train")


def _png(scene, i=0):
    return scene / "train" / f"r_{i}.png"


@pytest.mark.parametrize("bit_depth", [8, 16])
@pytest.mark.parametrize("keep", [0.5, -12, 20, 5])
def test_truncated_png(make_scene, bit_depth, keep):
    scene, _ = make_scene(bit_depth=bit_depth)
    p = _png(scene, 1)
    data = p.read_bytes()
    cut = int(len(data) * keep) if isinstance(keep, float) else (keep if keep > 0 else len(data) + keep)
    p.write_bytes(data[:cut])
    words = ["truncated"] if cut >= 8 else ["not a PNG"]
    _raises([p, *words], load_split, scene, "train")


@pytest.mark.parametrize("bit_depth", [8, 16])
def test_corrupt_png_crc(make_scene, bit_depth):
    scene, _ = make_scene(bit_depth=bit_depth)
    p = _png(scene)
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside IDAT
    p.write_bytes(bytes(data))
    _raises([p, "corrupt PNG", "CRC"], load_split, scene, "train")


def _rewrite_idat(data: bytes, new: bytes) -> bytes:
    """Replace the (single) IDAT payload of an encoder-written PNG, with a valid CRC."""
    start = 8 + 25
    (length,) = struct.unpack(">I", data[start : start + 4])
    assert data[start + 4 : start + 8] == b"IDAT"
    chunk = struct.pack(">I", len(new)) + b"IDAT" + new + struct.pack(">I", zlib.crc32(b"IDAT" + new) & 0xFFFFFFFF)
    return data[:start] + chunk + data[start + 12 + length :]


@pytest.mark.parametrize("bit_depth", [8, 16])
def test_corrupt_png_data_with_valid_crc(make_scene, bit_depth):
    scene, _ = make_scene(bit_depth=bit_depth)
    p = _png(scene)
    p.write_bytes(_rewrite_idat(p.read_bytes(), b"this is not zlib data"))
    _raises([p, "corrupt PNG"], load_split, scene, "train")


def test_png_with_too_little_pixel_data(make_scene):
    scene, _ = make_scene(bit_depth=16)
    p = _png(scene)
    p.write_bytes(_rewrite_idat(p.read_bytes(), zlib.compress(b"\0" * 10)))
    _raises([p, "truncated PNG", "pixel data"], load_split, scene, "train")


def test_png_with_bad_filter_type(make_scene):
    scene, _ = make_scene(bit_depth=16, h=2, w=2)
    p = _png(scene)
    p.write_bytes(_rewrite_idat(p.read_bytes(), zlib.compress(b"\x07" + b"\0" * 16 + b"\0" * 17)))
    _raises([p, "filter type 7"], load_split, scene, "train")


def test_not_a_png(make_scene):
    scene, _ = make_scene()
    _png(scene).write_text("hello")
    _raises([_png(scene), "not a PNG", "signature"], load_split, scene, "train")


def test_interlaced_16_bit_is_unsupported(make_scene):
    scene, _ = make_scene(bit_depth=16)
    p = _png(scene)
    data = bytearray(p.read_bytes())
    ihdr = bytes(data[12:29])
    ihdr = ihdr[:-1] + b"\x01"  # interlace method 1
    data[12:29] = ihdr
    data[29:33] = struct.pack(">I", zlib.crc32(ihdr) & 0xFFFFFFFF)
    p.write_bytes(bytes(data))
    _raises([p, "unsupported PNG", "interlaced"], load_split, scene, "train")


def test_unsupported_pixel_type(make_scene):
    import imageio.v3 as iio

    scene, _ = make_scene()
    tif = scene / "train" / "r_0.tif"
    iio.imwrite(tif, np.zeros((4, 6, 4), np.float32))
    path = _edit_json(scene, lambda m: m["frames"][0].update(file_path="./train/r_0.tif"))
    _raises([tif, "unsupported pixel type", "float32"], load_split, scene, "train")
    assert path.name == "transforms_train.json"


def test_unsupported_channel_count(tmp_path):
    _raises([tmp_path / "x", "channels", "(2, 2, 5)"], png.to_rgba_float, np.zeros((2, 2, 5), np.uint8), tmp_path / "x")


def test_write_split_rejects_bad_input(tmp_path, random_c2w, random_rgba):
    rng = np.random.default_rng(0)
    good_img, good_c2w = random_rgba(rng, 2, 3, 3), random_c2w(rng, 2)
    _raises(["images", "[N, H, W, 3|4]", "(2, 3, 3, 5)"], write_split, tmp_path, "train", np.zeros((2, 3, 3, 5)),
            good_c2w, 0.5)
    _raises(["c2ws", "(2, 4, 4)", "(3, 4, 4)"], write_split, tmp_path, "train", good_img, random_c2w(rng, 3), 0.5)
    bad = good_c2w.copy()
    bad[1, :3, :3] *= 1.1
    _raises(["c2ws", "[1]", "not orthonormal"], write_split, tmp_path, "train", good_img, bad, 0.5)
    nan = good_img.copy()
    nan[0, 0, 0, 0] = np.nan
    _raises(["images", "NaN"], write_split, tmp_path, "train", nan, good_c2w, 0.5)
    _raises(["images", "[0, 1]", "1.5"], write_split, tmp_path, "train", good_img * 1.5, good_c2w, 0.5)
    _raises(["camera_angle_x", "(0, pi)"], write_split, tmp_path, "train", good_img, good_c2w, float("inf"))
    _raises(["bit_depth", "12"], write_split, tmp_path, "train", good_img, good_c2w, 0.5, bit_depth=12)
    _raises(["uint16", "uint8"], write_split, tmp_path, "train", np.zeros((2, 3, 3, 4), np.uint8), good_c2w, 0.5,
            bit_depth=16)
    _raises(["split name", "'../x'"], write_split, tmp_path, "../x", good_img, good_c2w, 0.5)
    assert list(tmp_path.iterdir()) == []


def test_bad_downscale(make_scene):
    scene, _ = make_scene(h=4, w=6)
    _raises(["downscale", "integer >= 1", "0"], load_split, scene, "train", downscale=0)
    _raises(["downscale", "1.5"], load_split, scene, "train", downscale=1.5)
    _raises(["downscale", "factor 5", "6x4", scene / "transforms_train.json"], load_split, scene, "train", downscale=5)


def test_read_image_missing(tmp_path):
    _raises([tmp_path / "none.png", "image file does not exist"], read_image, tmp_path / "none.png")
