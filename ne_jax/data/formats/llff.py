"""Read an LLFF scene (``poses_bounds.npy``, as in the NeRF "real forward-facing" release) into a
:class:`~ne_jax.data.capture.Capture`.

Layout::

    <root>/poses_bounds.npy   # [N, 17]: per image a row-major 3x5 matrix, then near, far
    <root>/images/*.png|jpg   # N images, in the rows' order when sorted by name

Conventions (those of LLFF's ``imgs2poses`` and NeRF's ``load_llff.py``): the 3x5 matrix is a 3x4
camera-to-world whose rotation columns are the camera's ``[down, right, backwards]`` axes, and a
5th column ``(H, W, focal)`` in pixels of the full-resolution images. The reader reorders the axes
to OpenGL's ``[right, up, backwards]`` (new columns ``[col1, -col0, col2]``). When the files in
``images/`` have another size than ``H x W`` (a downscaled copy), the focal length is scaled by the
width ratio. The principal point is the image centre. ``near, far`` become each view's
``CaptureView.near_far``. Every 8th image is held out as the test split; there are no points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ne_jax.data.capture import Capture, CaptureView, holdout_splits
from ne_jax.data.formats._common import image_size, list_images, number, positive
from ne_jax.data.nerf_synthetic import check_rigid
from ne_jax.data.png import fail


def looks_like(root: Path) -> bool:
    """True when ``<root>/poses_bounds.npy`` exists."""
    return (Path(root) / "poses_bounds.npy").is_file()


def llff_to_opengl(pose_3x4: np.ndarray) -> np.ndarray:
    """``[..., 3, 4]`` LLFF camera-to-world (``[down, right, backwards]``) -> ``[..., 4, 4]``
    OpenGL camera-to-world (``[right, up, backwards]``)."""
    p = np.asarray(pose_3x4, dtype=np.float64)
    out = np.zeros(p.shape[:-2] + (4, 4))
    out[..., :3, 0] = p[..., :, 1]
    out[..., :3, 1] = -p[..., :, 0]
    out[..., :3, 2] = p[..., :, 2]
    out[..., :3, 3] = p[..., :, 3]
    out[..., 3, 3] = 1.0
    return out


def _load(path: Path) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise fail(path, None, "poses file does not exist") from None
    except (OSError, ValueError) as e:
        raise fail(path, None, f"cannot read the poses array: {e}") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise fail(
            path, None, f"expected an array [N, 17] (3x5 pose, near, far per image), found shape {np.shape(arr)}"
        )
    if not np.issubdtype(arr.dtype, np.number):
        raise fail(path, None, f"expected numbers, found dtype {arr.dtype}")
    return arr.astype(np.float64)


def read_llff(root: Path) -> Capture:
    """Read ``<root>/poses_bounds.npy`` and ``<root>/images`` (module docstring)."""
    root = Path(root)
    path, image_dir = root / "poses_bounds.npy", root / "images"
    arr = _load(path)
    if not image_dir.is_dir():
        raise fail(image_dir, None, f"image folder does not exist ({path} lists {len(arr)} images)")
    images = list_images(image_dir)
    if len(images) != len(arr):
        raise fail(
            path,
            None,
            f"expected one row per image: {len(arr)} rows, but {len(images)} images in {image_dir}",
        )
    views = []
    for i, (row, image) in enumerate(zip(arr, images)):
        where = f"row {i} ({image.name})"
        m = row[:15].reshape(3, 5)
        big_h = positive(number(m[0, 4], path, f"{where} H"), path, f"{where} H", "image height")
        big_w = positive(number(m[1, 4], path, f"{where} W"), path, f"{where} W", "image width")
        focal = positive(number(m[2, 4], path, f"{where} focal"), path, f"{where} focal", "focal length")
        near, far = (number(v, path, f"{where} {k}") for v, k in ((row[15], "near"), (row[16], "far")))
        if not 0.0 <= near < far:
            raise fail(path, where, f"expected bounds 0 <= near < far, found near {near!r}, far {far!r}")
        c2w = check_rigid(llff_to_opengl(m[:, :4]), path, f"{where} pose")
        w, h = image_size(image, path, where)
        scale = w / big_w
        if abs(h - big_h * scale) > 1.0:
            raise fail(
                path,
                where,
                f"image {image.name} is {w}x{h} (WxH), which is not the {big_w:g}x{big_h:g} of the poses "
                "or a downscaled copy of it (the aspect ratios differ)",
            )
        f = focal * scale
        views.append(
            CaptureView(
                name=image.name,
                image_path=image.resolve(),
                c2w=c2w,
                fx=f,
                fy=f,
                cx=0.5 * w,
                cy=0.5 * h,
                width=w,
                height=h,
                near_far=(near, far),
            )
        )
    return Capture(
        format="llff",
        root=root,
        views=tuple(views),
        splits=holdout_splits([v.name for v in views]),
        split_rule="every 8th held out",
        source=(str(path), str(image_dir)),
    )


read = read_llff

__all__ = ["llff_to_opengl", "looks_like", "read", "read_llff"]
