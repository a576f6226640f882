"""Writers of tiny scene folders in the COLMAP, nerfstudio, NSVF and LLFF layouts, for the format
reader tests (and any test that needs a real-format folder).

Each writer takes OpenGL camera-to-world matrices (the convention a :class:`Capture` holds) and
stores them in its format's own convention, so a reader must undo exactly that to pass.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

W, H = 16, 12
"""Image size of the fixture scenes (width, height)."""


def look_at(position, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``[4, 4]`` OpenGL camera-to-world of a camera at ``position`` looking at ``target``."""
    position, target, up = (np.asarray(v, dtype=np.float64) for v in (position, target, up))
    back = position - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, back, position
    return m


def circle_c2w(n: int = 10, radius: float = 4.0, height: float = 1.0) -> np.ndarray:
    """``[n, 4, 4]`` OpenGL camera-to-world, cameras on a circle around ``z`` looking at the origin."""
    angles = 2.0 * np.pi * np.arange(n) / n + 0.3
    return np.stack([look_at((radius * np.cos(a), radius * np.sin(a), height)) for a in angles])


def gl_to_cv(c2w: np.ndarray) -> np.ndarray:
    """OpenGL camera axes -> OpenCV (flip the camera's ``y``, ``z``); its own inverse."""
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[..., :3, 1:3] *= -1.0
    return out


def write_images(folder: Path, names, width: int = W, height: int = H, seed: int = 0) -> list[Path]:
    """Small random RGB images (format from each name's suffix: PNG or JPEG)."""
    rng = np.random.default_rng(seed)
    paths = []
    for name in names:
        p = Path(folder) / name
        p.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 256, (height, width, 3), dtype=np.uint8)).save(p)
        paths.append(p)
    return paths


def rotation_to_qvec(r: np.ndarray) -> np.ndarray:
    """``[3, 3]`` rotation -> unit quaternion ``(w, x, y, z)`` (COLMAP's order), ``w >= 0``."""
    r = np.asarray(r, dtype=np.float64)
    k = (
        np.array(
            [
                [r[0, 0] - r[1, 1] - r[2, 2], 0, 0, 0],
                [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], 0, 0],
                [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1], 0],
                [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], r[0, 0] + r[1, 1] + r[2, 2]],
            ]
        )
        / 3.0
    )
    vals, vecs = np.linalg.eigh(k)
    x, y, z, w = vecs[:, np.argmax(vals)]
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


# ----------------------------------------------------------------------------------------------
# COLMAP
# ----------------------------------------------------------------------------------------------


def write_colmap_text(
    root: Path,
    c2w_gl: np.ndarray,
    names,
    cameras=((1, "PINHOLE", W, H, (20.0, 21.0, 8.0, 6.0)),),
    camera_of_image=None,
    points=None,
    model_dir: str = "sparse/0",
    images: bool = True,
) -> Path:
    """A COLMAP text model (cameras.txt, images.txt, points3D.txt) under ``root/model_dir`` and,
    with ``images``, the images in ``root/images``. ``cameras``: ``(id, model, w, h, params)``;
    ``camera_of_image`` the camera id of each image (default: the first camera); ``points``
    ``(xyz [P, 3], rgb uint8 [P, 3], error [P])``. Returns the model folder."""
    root = Path(root)
    d = root / model_dir
    d.mkdir(parents=True, exist_ok=True)
    cam_lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for cid, model, w, h, params in cameras:
        cam_lines.append(" ".join([str(cid), model, str(w), str(h), *(repr(float(p)) for p in params)]))
    (d / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    camera_of_image = camera_of_image or [cameras[0][0]] * len(names)
    img_lines = ["# Image list with two lines of data per image:"]
    num_points = 0 if points is None else len(points[0])
    for i, (m, name) in enumerate(zip(c2w_gl, names)):
        w2c = np.linalg.inv(gl_to_cv(m))
        q = rotation_to_qvec(w2c[:3, :3])
        t = w2c[:3, 3]
        vals = " ".join(repr(float(v)) for v in (*q, *t))
        img_lines.append(f"{i + 1} {vals} {camera_of_image[i]} {name}")
        # the first image observes every point (its 2D point j is point j + 1's track)
        img_lines.append(" ".join(f"1.5 2.5 {j + 1}" for j in range(num_points)) if i == 0 else "")
    (d / "images.txt").write_text("\n".join(img_lines) + "\n")
    pt_lines = ["# 3D point list with one line of data per point:"]
    if points is not None:
        xyz, rgb, err = points
        for j in range(len(xyz)):
            coords = " ".join(repr(float(v)) for v in xyz[j])
            colour = " ".join(str(int(c)) for c in rgb[j])
            pt_lines.append(f"{j + 1} {coords} {colour} {float(err[j])!r} 1 {j}")
    (d / "points3D.txt").write_text("\n".join(pt_lines) + "\n")
    if images:
        write_images(root / "images", names, cameras[0][2], cameras[0][3])
    return d


def text_to_binary(model: Path) -> Path:
    """Rewrite a text model in ``model`` as COLMAP binary (read and written by pycolmap), removing
    the text files."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model))
    tmp = model.parent / (model.name + "_bin")
    tmp.mkdir()
    rec.write_binary(str(tmp))
    shutil.rmtree(model)
    tmp.rename(model)
    return model


def default_points(n: int = 5, seed: int = 1):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3))
    rgb = rng.integers(0, 256, (n, 3))
    err = rng.random(n)
    return xyz, rgb, err


# ----------------------------------------------------------------------------------------------
# nerfstudio
# ----------------------------------------------------------------------------------------------


def write_nerfstudio(
    root: Path,
    c2w_gl: np.ndarray,
    names,
    intrinsics=None,
    frame_extra=None,
    meta_extra=None,
    images: bool = True,
) -> Path:
    """``root/transforms.json`` with ``frames[i].file_path = names[i]`` and ``transform_matrix``
    the OpenGL camera-to-world as is; ``intrinsics`` (global keys, default a pinhole with ``w``,
    ``h``), ``frame_extra[i]`` merged into frame ``i``, ``meta_extra`` into the top level."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    meta = dict(
        intrinsics if intrinsics is not None else {"fl_x": 20.0, "fl_y": 21.0, "cx": 8.0, "cy": 6.0, "w": W, "h": H}
    )
    frames = []
    for i, (m, name) in enumerate(zip(c2w_gl, names)):
        frame = {"file_path": name, "transform_matrix": np.asarray(m).tolist()}
        if frame_extra is not None:
            frame.update(frame_extra[i])
        frames.append(frame)
    meta["frames"] = frames
    meta.update(meta_extra or {})
    path = root / "transforms.json"
    path.write_text(json.dumps(meta, indent=1))
    if images:
        write_images(root, [n.removeprefix("./") for n in names])
    return path


# ----------------------------------------------------------------------------------------------
# NSVF
# ----------------------------------------------------------------------------------------------


def write_nsvf(
    root: Path, c2w_gl: np.ndarray, names, focal=20.0, cx=8.0, cy=6.0, matrix_form=False, bbox=None, images=True
) -> Path:
    """``intrinsics.txt`` (the one-line ``f cx cy 0.`` form, or with ``matrix_form`` a 4x4 K with
    ``focal`` a ``(fx, fy)`` pair allowed), ``pose/<stem>.txt`` (OpenCV camera-to-world) and
    ``rgb/<name>``; ``bbox`` ``(lo, hi)`` writes ``bbox.txt`` with a voxel size."""
    root = Path(root)
    (root / "pose").mkdir(parents=True, exist_ok=True)
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    fx, fy = (focal, focal) if np.isscalar(focal) else focal
    if matrix_form:
        k = np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)
        text = "\n".join(" ".join(repr(float(v)) for v in row) for row in k)
    else:
        text = f"{fx!r} {cx!r} {cy!r} 0.\n0. 0. 0.\n1.\n{H} {W}"
    (root / "intrinsics.txt").write_text(text + "\n")
    for m, name in zip(c2w_gl, names):
        pose = gl_to_cv(m)
        stem = Path(name).stem
        (root / "pose" / f"{stem}.txt").write_text(
            "\n".join(" ".join(repr(float(v)) for v in row) for row in pose) + "\n"
        )
    if bbox is not None:
        lo, hi = bbox
        (root / "bbox.txt").write_text(" ".join(repr(float(v)) for v in (*lo, *hi)) + " 0.1\n")
    if images:
        write_images(root / "rgb", names)
    return root


# ----------------------------------------------------------------------------------------------
# LLFF
# ----------------------------------------------------------------------------------------------


def gl_to_llff(c2w_gl: np.ndarray) -> np.ndarray:
    """``[..., 4, 4]`` OpenGL camera-to-world -> ``[..., 3, 4]`` LLFF ``[down, right, backwards]``."""
    m = np.asarray(c2w_gl, dtype=np.float64)
    out = np.empty(m.shape[:-2] + (3, 4))
    out[..., :, 0] = -m[..., :3, 1]  # down = -up
    out[..., :, 1] = m[..., :3, 0]  # right
    out[..., :, 2] = m[..., :3, 2]  # backwards
    out[..., :, 3] = m[..., :3, 3]
    return out


def write_llff(
    root: Path,
    c2w_gl: np.ndarray,
    hwf=(2 * H, 2 * W, 40.0),
    bounds=None,
    image_size=(W, H),
    ext: str = ".jpg",
    images: bool = True,
) -> np.ndarray:
    """``root/poses_bounds.npy`` for ``c2w_gl`` with full-resolution ``hwf = (H, W, focal)``, and
    images ``images/img_<i>.<ext>`` of ``image_size`` (W, H); returns the ``[N, 17]`` array."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    n = len(c2w_gl)
    bounds = np.asarray(bounds if bounds is not None else [[1.0 + 0.1 * i, 8.0 + i] for i in range(n)])
    poses = np.concatenate([gl_to_llff(c2w_gl), np.broadcast_to(np.asarray(hwf, float)[:, None], (n, 3, 1))], axis=2)
    arr = np.concatenate([poses.reshape(n, 15), bounds], axis=1)
    np.save(root / "poses_bounds.npy", arr)
    if images:
        write_images(root / "images", [f"img_{i:03d}{ext}" for i in range(n)], *image_size)
    return arr
