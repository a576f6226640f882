"""Error by region: labels on a drawn scene, where an error placed in one region is counted, the
shares, the picture and bad input."""

import numpy as np
import pytest

from ne_jax.eval.regions import REGIONS, error_map_picture, label_regions, region_errors, view_shares

BG = np.ones(3, np.float32)


def _scene(size=48):
    """A red disc (radius 16) with dark stripes on its left half and one bright spot, on white."""
    y, x = np.mgrid[:size, :size].astype(np.float32)
    r = np.hypot(x - 24, y - 24)
    alpha = (r <= 16).astype(np.float32)
    rgb = np.tile(np.array([0.7, 0.2, 0.2], np.float32), (size, size, 1))
    stripes = (x < 20) & ((y // 3) % 2 == 0)
    rgb[stripes] = (0.2, 0.05, 0.05)
    spot = np.hypot(x - 30, y - 22) <= 1.5
    rgb[spot] = (1.0, 0.95, 0.95)
    target = alpha[..., None] * rgb + (1 - alpha[..., None]) * BG
    return target, alpha, stripes, spot


def test_labels_follow_the_drawing():
    target, alpha, stripes, spot = _scene()
    labels = label_regions(target, alpha, target, BG)
    name = lambda y, x: REGIONS[labels[y, x]]  # noqa: E731
    assert name(24, 8) == "silhouette" and name(24, 40) == "silhouette"  # on the disc's edge
    assert name(22, 30) == "highlight"  # the spot's centre
    assert name(24, 12) == "texture"  # inside the stripes
    assert name(30, 30) == "flat" and name(2, 2) == "background"
    assert not (labels == REGIONS.index("hole")).any()  # the render is the ground truth: no hole


def test_an_error_is_counted_where_it_is():
    target, alpha, stripes, spot = _scene()
    pred = target.copy()
    pred[26:30, 26:30] = BG  # a piece of the flat interior rendered as background
    labels = label_regions(target, alpha, pred, BG)
    assert (labels[26:30, 26:30] == REGIONS.index("hole")).all()
    r = region_errors(labels, pred, target)
    assert r["hole"]["error"] == pytest.approx(1.0) and r["flat"]["error"] == 0.0
    assert sum(v["pixels"] for v in r.values()) == pytest.approx(1.0)
    assert r["hole"]["pixels"] == pytest.approx(16 / 48**2)
    mse = np.mean((pred[26:30, 26:30] - target[26:30, 26:30]) ** 2)
    assert r["hole"]["psnr"] == pytest.approx(-10 * np.log10(mse), rel=1e-6)
    assert r["background"]["psnr"] == pytest.approx(100.0)  # no error there: the MSE floor
    # several views at once: the same numbers for the view stacked twice
    both = region_errors(np.stack([labels, labels]), np.stack([pred, pred]), np.stack([target, target]))
    assert both["hole"] == pytest.approx(r["hole"])


def test_picture_panels():
    target, alpha, _, _ = _scene()
    labels = label_regions(target, alpha, target, BG)
    pic = error_map_picture(target, target, labels)
    assert pic.shape == (48, 4 * 48, 3)
    np.testing.assert_array_equal(pic[:, :48], target)
    assert pic[:, 96:144].max() == 0.0  # no error: a black heat map


def test_bad_shapes_are_named():
    target, alpha, _, _ = _scene()
    with pytest.raises(ValueError, match=r"alpha: expected shape \[48, 48\], found \[48, 47\]"):
        label_regions(target, alpha[:, :47], target, BG)
    with pytest.raises(ValueError, match="pred: expected shape"):
        label_regions(target, alpha, target[..., :2], BG)
    with pytest.raises(ValueError, match="labels: expected the images' shape"):
        region_errors(np.zeros((4, 4), np.int8), target, target)


def test_a_pixel_behind_its_neighbours_is_see_through():
    """A ray that passed the surface its neighbours stop at (rendered depth behind their median) is
    ``see_through``; the same render without a depth map is not, nor is a smooth slope of depth."""
    target, alpha, _, _ = _scene()
    pred = target.copy()
    pred[30, 30] = (0.1, 0.1, 0.1)  # a dark dot: the far side of the object shows through
    y, x = np.mgrid[:48, :48].astype(np.float32)
    depth = np.where(alpha > 0, 3.0 + 0.005 * x, 0.0).astype(np.float32)  # a tilted surface: no pixel behind
    assert not (label_regions(target, alpha, pred, BG, depth=depth) == REGIONS.index("see_through")).any()
    depth[30, 30] = 3.4
    labels = label_regions(target, alpha, pred, BG, depth=depth)
    assert REGIONS[labels[30, 30]] == "see_through"
    assert (labels == REGIONS.index("see_through")).sum() == 1
    assert REGIONS[label_regions(target, alpha, pred, BG)[30, 30]] == "flat"  # no depth map: not decided
    assert region_errors(labels, pred, target)["see_through"]["error"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match=r"depth: expected shape \[48, 48\], found \[48, 47\]"):
        label_regions(target, alpha, pred, BG, depth=depth[:, :47])


def test_view_shares_count_each_views_pixels():
    """``view_shares``: per view the share of its pixels in one region (the hole goal of a test view);
    an unknown region is named."""
    labels = np.full((3, 4, 5), REGIONS.index("flat"))
    labels[1, 0, :2] = REGIONS.index("hole")  # 2 of 20 pixels
    labels[2] = REGIONS.index("hole")
    np.testing.assert_allclose(view_shares(labels, "hole"), [0.0, 0.1, 1.0])
    with pytest.raises(ValueError, match="'holes'"):
        view_shares(labels, "holes")
