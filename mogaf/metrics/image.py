"""PSNR and SSIM, plain and masked, as DyCheck defines them.

Images are float arrays in [0, 1] of shape (H, W, C) (normally C = 3), given
as numpy arrays or torch tensors (moved to the CPU, computed in float64).
Masks are (H, W) or (H, W, 1), boolean or float in [0, 1]; 1 marks the pixels
that count (DyCheck's co-visibility mask). Results are Python floats.

Definitions (DyCheck, `dycheck/core/metrics/image.py`, Gao et al. 2022; the
Shape-of-Motion evaluation, `flow3d/metrics.py`, uses the same ones):

* masked mean: ``masked_mean(x, m) = sum(x * m) / sum(m)`` with ``m``
  broadcast to ``x`` (so for an (H, W, 3) error and an (H, W) mask the
  denominator is ``3 * sum(m)``). Soft masks weight pixels.
* PSNR / mPSNR: ``-10 * log10(masked_mean((img0 - img1) ** 2, m))`` (a peak
  value of 1). Without a mask ``m = 1`` everywhere, i.e. the usual PSNR on the
  mean squared error over all pixels and channels. Identical images give
  ``+inf``.
* SSIM / mSSIM: see `ssim`. `ssim_padded` is the SSIM of GaussianPrediction's
  evaluation (3DGS's zero-padded window), the D-NeRF protocol's.

DyCheck evaluates 8-bit-quantised images (``round(255 x) / 255``); quantise
before calling to reproduce its numbers. Per-frame values are averaged over
frames by the caller, as DyCheck and Shape-of-Motion do.

Degenerate inputs: an empty mask (no positive weight) raises `MogafError`, as
do mismatched shapes, non-float images, non-finite values, and images smaller
than the SSIM window.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import correlate1d

from mogaf.errors import MogafError
from mogaf.metrics.content_cache import ContentCache, content_key

__all__ = ["masked_mean", "psnr", "mpsnr", "ssim", "mssim", "ssim_padded", "gaussian_window"]


def _as_numpy(x, what: str) -> np.ndarray:
    """numpy view of a numpy array or torch tensor (detached, on the CPU)."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # torch.Tensor, without importing torch
        x = x.detach().cpu().numpy()
    arr = np.asarray(x)
    if arr.dtype == object:
        raise MogafError(f"{what}: expected a numeric array, got {type(x).__name__}")
    return arr


def _image(x, what: str) -> np.ndarray:
    arr = _as_numpy(x, what)
    if arr.ndim != 3:
        raise MogafError(f"{what}: expected an image of shape (H, W, C), got shape {tuple(arr.shape)}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise MogafError(
            f"{what}: expected a float image in [0, 1], got dtype {arr.dtype} (divide 8-bit images by 255)"
        )
    arr = arr.astype(np.float64, copy=False)
    if not np.isfinite(arr).all():
        raise MogafError(f"{what}: image has non-finite values")
    return arr


def _pair(img0, img1) -> tuple[np.ndarray, np.ndarray]:
    a = _image(img0, "img0")
    b = _image(img1, "img1")
    if a.shape != b.shape:
        raise MogafError(f"images differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")
    return a, b


def _mask(mask, hw: tuple[int, int]) -> np.ndarray:
    """(H, W) float64 mask in [0, 1]; raises on bad shape, range or emptiness."""
    m = _as_numpy(mask, "mask")
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if m.shape != tuple(hw):
        raise MogafError(
            f"mask: expected shape {tuple(hw)} or {tuple(hw) + (1,)}, got {tuple(_as_numpy(mask, 'mask').shape)}"
        )
    m = m.astype(np.float64)
    if not np.isfinite(m).all() or m.min() < 0.0 or m.max() > 1.0:
        raise MogafError("mask: values must lie in [0, 1]")
    if not (m > 0).any():
        raise MogafError("mask is empty (no pixel has positive weight); the masked metric is undefined")
    return m


def masked_mean(x, mask=None) -> float:
    """``sum(x * m) / sum(m)``, ``m`` broadcast to the shape of ``x``.

    ``mask=None`` gives the plain mean. An empty mask (``sum(m) == 0``) raises
    `MogafError` instead of DyCheck's silent division by ``1e-6``.
    """
    xa = _as_numpy(x, "x").astype(np.float64)
    if mask is None:
        if xa.size == 0:
            raise MogafError("masked_mean: empty input")
        return float(xa.mean())
    m = _as_numpy(mask, "mask").astype(np.float64)
    if m.ndim == xa.ndim - 1 and xa.ndim >= 1:
        m = m[..., None]
    try:
        m = np.broadcast_to(m, xa.shape)
    except ValueError:
        raise MogafError(f"mask of shape {tuple(m.shape)} does not broadcast to {tuple(xa.shape)}") from None
    if not np.isfinite(m).all() or (m < 0).any():
        raise MogafError("mask: values must be finite and non-negative")
    total = float(m.sum())
    if total <= 0.0:
        raise MogafError("mask is empty (no pixel has positive weight); the masked mean is undefined")
    return float((xa * m).sum() / total)


def psnr(img0, img1, mask=None) -> float:
    """PSNR in dB for images in [0, 1]: ``-10 log10(MSE)``.

    With ``mask`` this is DyCheck's mPSNR: the MSE is the masked mean of the
    squared error over the masked pixels and all channels (see the module
    docstring). Identical images (over the mask) give ``+inf``.
    """
    a, b = _pair(img0, img1)
    m = None if mask is None else _mask(mask, a.shape[:2])
    mse = masked_mean((a - b) ** 2, m)
    if mse <= 0.0:
        return math.inf
    return -10.0 * math.log10(mse)


def mpsnr(img0, img1, mask) -> float:
    """Masked PSNR (DyCheck mPSNR); ``mask`` is required. See `psnr`."""
    if mask is None:
        raise MogafError("mpsnr needs a mask (use psnr for the unmasked metric)")
    return psnr(img0, img1, mask)


def gaussian_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """Normalised 1-D Gaussian taps, centred as DyCheck/tf.image.ssim centre them."""
    if size < 1 or sigma <= 0:
        raise MogafError(f"SSIM window needs size >= 1 and sigma > 0, got size={size}, sigma={sigma}")
    hw = size // 2
    shift = (2 * hw - size + 1) / 2  # 0 for odd sizes, 0.5 for even ones
    t = (np.arange(size, dtype=np.float64) - hw + shift) / sigma
    f = np.exp(-0.5 * t**2)
    return f / f.sum()


def _valid_filter(z: np.ndarray, taps: np.ndarray, axis: int) -> np.ndarray:
    """'valid' 1-D correlation of ``z`` with ``taps`` along ``axis``.

    The output is shorter by ``len(taps) - 1`` along ``axis``. (DyCheck uses a
    true convolution; the Gaussian and box taps are symmetric, so they agree.)
    """
    n = len(taps)
    # scipy centres the taps on index n // 2: full[i] = sum_j taps[j] z[i + j - n // 2].
    full = correlate1d(z, taps, axis=axis, mode="constant", cval=0.0)
    left = n // 2
    stop = z.shape[axis] - (n - 1 - left)
    index = [slice(None)] * z.ndim
    index[axis] = slice(left, stop)
    return full[tuple(index)]


def _partial_blur(z: np.ndarray, m: np.ndarray, taps: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """One 1-D pass of the partial convolution (Liu et al. 2018, Sec. 3.1): the
    plain reference `PartialBlur`, which ssim uses, is tested against.

    ``z``: (H, W, C), ``m``: (H, W). Returns the blurred values
    ``where(S_m != 0, G*(z m) * n / S_m, 0)`` and the new mask ``S_m != 0``,
    where ``G*`` is the Gaussian 'valid' filter, ``S_m`` the plain sum of ``m``
    over the same window and ``n`` the window length.
    """
    n = len(taps)
    num = _valid_filter(z * m[..., None], taps, axis)
    cover = _valid_filter(m, np.ones(n), axis)
    ok = cover != 0
    out = np.where(ok[..., None], num * n / np.where(ok, cover, 1.0)[..., None], 0.0)
    return out, ok.astype(np.float64)


class PartialBlur:
    """`_partial_blur` along the width, then along the height, for one mask.

    The mask's window counts are computed once for every image blurred with
    it, and the steps that change nothing for a full mask or a covered window
    are skipped (``z * 1.0`` is ``z``, ``where(True, x, 0)`` is ``x``): the same
    values as the two `_partial_blur` passes, to the bit (tested)."""

    def __init__(self, m: np.ndarray, taps: np.ndarray) -> None:
        self.taps = taps
        self.n = len(taps)
        self.passes = []
        weights = np.array(m, dtype=np.float64)  # a copy: kept, so the caller's mask may change
        for axis in (1, 0):
            cover = _valid_filter(weights, np.ones(self.n), axis)
            ok = cover != 0
            self.passes.append(
                (
                    axis,
                    None if bool((weights == 1.0).all()) else weights[..., None],
                    np.where(ok, cover, 1.0)[..., None],
                    None if bool(ok.all()) else ok[..., None],
                )
            )
            weights = ok.astype(np.float64)
        self.nbytes = sum(sum(a.nbytes for a in p[1:] if a is not None) for p in self.passes)

    def __call__(self, z: np.ndarray) -> np.ndarray:
        for axis, weights, cover, ok in self.passes:
            num = _valid_filter(z if weights is None else z * weights, self.taps, axis)
            z = num * self.n / cover
            if ok is not None:
                z = np.where(ok, z, 0.0)
        return z


# The ground truth's blurred mean and square under its mask, by content: every
# method's render is compared with the same ground-truth images.
REFERENCE_STATISTICS = ContentCache(256 << 20)


def _reference_statistics(b: np.ndarray, m: np.ndarray, taps: np.ndarray) -> tuple[PartialBlur, np.ndarray, np.ndarray]:
    def make():
        blur = PartialBlur(m, taps)
        return blur, blur(b), blur(b * b)

    key = content_key(b, m, taps)
    return REFERENCE_STATISTICS.get(key, make, lambda v: v[0].nbytes + v[1].nbytes + v[2].nbytes)


def ssim(
    img0,
    img1,
    mask=None,
    *,
    max_val: float = 1.0,
    filter_size: int = 11,
    filter_sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> float:
    """SSIM (Wang et al. 2004) exactly as DyCheck's `compute_ssim` computes it.

    Local statistics come from a separable Gaussian window (11 taps, sigma
    1.5, normalised) applied in 'valid' mode, i.e. only where the window fits
    inside the image; each channel is filtered on its own. Per window
    position and channel::

        mu0 = G(x0), mu1 = G(x1)
        s00 = max(G(x0^2) - mu0^2, 0), s11 = max(G(x1^2) - mu1^2, 0)
        s01 = sign(G(x0 x1) - mu0 mu1) * min(sqrt(s00 s11), |G(x0 x1) - mu0 mu1|)
        ssim = (2 mu0 mu1 + c1)(2 s01 + c2) / ((mu0^2 + mu1^2 + c1)(s00 + s11 + c2))

    with ``c1 = (k1 max_val)^2``, ``c2 = (k2 max_val)^2``. The result is the
    mean of this map over all (H - 10) x (W - 10) x C entries.

    Masked (mSSIM): every blur ``G`` becomes DyCheck's partial convolution,
    applied first along the width and then along the height. Each 1-D pass
    filters ``z * m`` with the Gaussian, divides by the plain count ``S_m`` of
    the mask inside the window and multiplies by the window length (11); where
    the window holds no mask at all the output is 0, and the next pass uses the
    binary mask ``S_m != 0``. Pixels with ``m = 0`` therefore never influence
    the result. Note the DyCheck convention kept here on purpose: the final
    mean runs over the whole map, and window positions with no masked pixel
    have ``mu = s = 0`` and so contribute exactly 1. With a full mask the
    masked and plain SSIM coincide.
    """
    a, b = _pair(img0, img1)
    h, w = a.shape[:2]
    if h < filter_size or w < filter_size:
        raise MogafError(f"SSIM needs images of at least {filter_size}x{filter_size} px, got {h}x{w}")
    m = np.ones((h, w)) if mask is None else _mask(mask, (h, w))
    taps = gaussian_window(filter_size, filter_sigma)

    blur, mu1, blur11 = _reference_statistics(b, m, taps)
    mu0 = blur(a)
    mu00, mu11, mu01 = mu0 * mu0, mu1 * mu1, mu0 * mu1
    s00 = np.maximum(blur(a * a) - mu00, 0.0)
    s11 = np.maximum(blur11 - mu11, 0.0)
    s01 = blur(a * b) - mu01
    s01 = np.sign(s01) * np.minimum(np.sqrt(s00 * s11), np.abs(s01))
    c1 = (k1 * max_val) ** 2
    c2 = (k2 * max_val) ** 2
    ssim_map = ((2 * mu01 + c1) * (2 * s01 + c2)) / ((mu00 + mu11 + c1) * (s00 + s11 + c2))
    return float(ssim_map.mean())


def ssim_padded(
    img0,
    img1,
    *,
    max_val: float = 1.0,
    filter_size: int = 11,
    filter_sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> float:
    """SSIM as GaussianPrediction's `metrics.py` computes it (3DGS's
    `utils/loss_utils.ssim`): the Gaussian window of `ssim`, but applied at
    every pixel with the image zero-padded by half a window ('same' size), the
    variances and covariance used as they come (no clamping), and the mean of
    the map over all H x W x C entries, borders included::

        ssim = (2 mu0 mu1 + c1)(2 (G(x0 x1) - mu0 mu1) + c2)
               / ((mu0^2 + mu1^2 + c1)(G(x0^2) - mu0^2 + G(x1^2) - mu1^2 + c2))

    The D-NeRF protocol (MuJoCo) reports this SSIM, as the paper's D-NeRF
    table does; the iPhone protocol reports DyCheck's (`ssim`)."""
    a, b = _pair(img0, img1)
    taps = gaussian_window(filter_size, filter_sigma)

    def blur(z: np.ndarray) -> np.ndarray:
        # a separable kernel on a zero-padded image: a zero-padded 1-D pass per axis
        return correlate1d(
            correlate1d(z, taps, axis=1, mode="constant", cval=0.0), taps, axis=0, mode="constant", cval=0.0
        )

    mu0, mu1 = blur(a), blur(b)
    mu00, mu11, mu01 = mu0 * mu0, mu1 * mu1, mu0 * mu1
    c1 = (k1 * max_val) ** 2
    c2 = (k2 * max_val) ** 2
    num = (2 * mu01 + c1) * (2 * (blur(a * b) - mu01) + c2)
    den = (mu00 + mu11 + c1) * (blur(a * a) - mu00 + blur(b * b) - mu11 + c2)
    return float((num / den).mean())


def mssim(img0, img1, mask, **kwargs) -> float:
    """Masked SSIM (DyCheck mSSIM, partial convolution); ``mask`` is required. See `ssim`."""
    if mask is None:
        raise MogafError("mssim needs a mask (use ssim for the unmasked metric)")
    return ssim(img0, img1, mask, **kwargs)
