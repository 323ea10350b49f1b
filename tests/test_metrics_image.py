"""PSNR / SSIM and their DyCheck-masked versions, and GaussianPrediction's SSIM, against hand values and brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mogaf.errors import MogafError
from mogaf.metrics import gaussian_window, masked_mean, mpsnr, mssim, psnr, ssim, ssim_padded

C1 = 0.01**2
C2 = 0.03**2


def test_psnr_hand_values():
    a = np.zeros((8, 9, 3))
    assert psnr(a, a + 0.1) == pytest.approx(20.0)
    assert psnr(a, a + 0.01) == pytest.approx(40.0)
    assert psnr(a, a) == math.inf
    # One channel off by 0.3: MSE = 0.09 / 3 = 0.03.
    b = a.copy()
    b[..., 1] = 0.3
    assert psnr(a, b) == pytest.approx(-10 * math.log10(0.03))


def test_mpsnr_counts_only_the_mask():
    a = np.zeros((4, 4, 3))
    b = np.full((4, 4, 3), 0.5)
    b[:2] = 0.1  # rows 0-1: error 0.1, rows 2-3: error 0.5
    mask = np.zeros((4, 4), bool)
    mask[:2] = True
    assert mpsnr(a, b, mask) == pytest.approx(20.0)
    assert mpsnr(a, b, mask[..., None].astype(np.float32)) == pytest.approx(20.0)
    # Soft mask: weights 1 on rows 0-1, 0.5 on rows 2-3.
    soft = np.where(mask, 1.0, 0.5)
    mse = (8 * 0.01 + 8 * 0.5 * 0.25) / (8 + 8 * 0.5)
    assert mpsnr(a, b, soft) == pytest.approx(-10 * math.log10(mse))
    # Error only outside the mask: a perfect score.
    assert mpsnr(a, np.where(mask[..., None], 0.0, np.full_like(a, 0.7)), mask) == math.inf


def test_masked_mean_definition():
    x = np.arange(12.0).reshape(2, 2, 3)
    m = np.array([[1.0, 0.0], [0.0, 0.5]])
    expected = (x[0, 0].sum() + 0.5 * x[1, 1].sum()) / (3 * 1.5)
    assert masked_mean(x, m) == pytest.approx(expected)
    assert masked_mean(x) == pytest.approx(x.mean())
    with pytest.raises(MogafError, match="empty"):
        masked_mean(x, np.zeros((2, 2)))


def test_empty_and_malformed_inputs_raise_one_line_errors():
    a = np.zeros((16, 16, 3))
    for fn in (mpsnr, mssim):
        with pytest.raises(MogafError, match="empty") as err:
            fn(a, a, np.zeros((16, 16)))
        assert "\n" not in str(err.value)
    with pytest.raises(MogafError, match="shape"):
        psnr(a, np.zeros((16, 15, 3)))
    with pytest.raises(MogafError, match="mask"):
        mpsnr(a, a, np.ones((15, 16)))
    with pytest.raises(MogafError, match="255"):
        psnr(a.astype(np.uint8), a.astype(np.uint8))
    with pytest.raises(MogafError, match="non-finite"):
        ssim(a, np.full_like(a, np.nan))
    with pytest.raises(MogafError, match="at least 11x11"):
        ssim(np.zeros((10, 30, 3)), np.zeros((10, 30, 3)))
    with pytest.raises(MogafError, match="needs a mask"):
        mssim(a, a, None)


def test_gaussian_window():
    f = gaussian_window(11, 1.5)
    assert f.sum() == pytest.approx(1.0)
    assert np.argmax(f) == 5 and np.allclose(f, f[::-1])
    assert f[4] / f[5] == pytest.approx(math.exp(-0.5 / 1.5**2))


def test_ssim_of_constant_images_is_the_luminance_term():
    a, b = 0.2, 0.7
    x = np.full((15, 17, 3), a)
    y = np.full((15, 17, 3), b)
    assert ssim(x, y) == pytest.approx((2 * a * b + C1) / (a * a + b * b + C1))
    assert ssim(x, x) == pytest.approx(1.0)


def _brute_ssim(x, y, mask, size=11, sigma=1.5):
    """Independent loop version of DyCheck's SSIM with partial-convolution masking."""
    g = gaussian_window(size, sigma)

    def blur(z):
        h, w, c = z.shape
        # Pass 1, along the width.
        z1 = np.zeros((h, w - size + 1, c))
        m1 = np.zeros((h, w - size + 1))
        for i in range(h):
            for j in range(w - size + 1):
                cnt = mask[i, j : j + size].sum()
                if cnt != 0:
                    for k in range(size):
                        z1[i, j] += g[k] * z[i, j + k] * mask[i, j + k]
                    z1[i, j] *= size / cnt
                    m1[i, j] = 1.0
        # Pass 2, along the height, on the binary mask of pass 1.
        z2 = np.zeros((h - size + 1, w - size + 1, c))
        for i in range(h - size + 1):
            for j in range(w - size + 1):
                cnt = m1[i : i + size, j].sum()
                if cnt != 0:
                    for k in range(size):
                        z2[i, j] += g[k] * z1[i + k, j] * m1[i + k, j]
                    z2[i, j] *= size / cnt
        return z2

    mu0, mu1 = blur(x), blur(y)
    s00 = np.maximum(blur(x * x) - mu0**2, 0)
    s11 = np.maximum(blur(y * y) - mu1**2, 0)
    s01 = blur(x * y) - mu0 * mu1
    s01 = np.sign(s01) * np.minimum(np.sqrt(s00 * s11), np.abs(s01))
    smap = (2 * mu0 * mu1 + C1) * (2 * s01 + C2) / ((mu0**2 + mu1**2 + C1) * (s00 + s11 + C2))
    return smap.mean()


def test_ssim_matches_plain_2d_gaussian_definition(rng):
    x = rng.random((19, 23, 3))
    y = np.clip(x + 0.2 * rng.standard_normal(x.shape), 0, 1)
    g = gaussian_window()
    g2 = np.outer(g, g)

    def blur(z):
        h, w = z.shape[0] - 10, z.shape[1] - 10
        return np.stack(
            [[np.tensordot(g2, z[i : i + 11, j : j + 11], axes=([0, 1], [0, 1])) for j in range(w)] for i in range(h)]
        )

    mu0, mu1 = blur(x), blur(y)
    s00, s11 = blur(x * x) - mu0**2, blur(y * y) - mu1**2
    s01 = blur(x * y) - mu0 * mu1
    smap = (2 * mu0 * mu1 + C1) * (2 * s01 + C2) / ((mu0**2 + mu1**2 + C1) * (s00 + s11 + C2))
    assert ssim(x, y) == pytest.approx(smap.mean(), abs=1e-12)
    assert ssim(x, y) < 0.9  # the noise is visible to SSIM
    assert ssim(x, y) == pytest.approx(ssim(y, x), abs=1e-12)


def test_ssim_padded_is_a_2d_convolution_of_the_zero_padded_images(rng):
    """GaussianPrediction's metrics.py (3DGS's loss_utils.ssim): torch conv2d
    with a 11x11 Gaussian (sigma 1.5) and zero padding 5, per channel, the
    mean of the whole map; here in float64 with the window written out."""
    x = rng.random((17, 26, 3))
    y = np.clip(x + 0.2 * rng.standard_normal(x.shape), 0, 1)
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    g /= g.sum()
    window = torch.from_numpy(np.outer(g, g))[None, None].repeat(3, 1, 1, 1)

    def blur(z):
        return torch.nn.functional.conv2d(torch.from_numpy(z).permute(2, 0, 1)[None], window, padding=5, groups=3)

    mu0, mu1 = blur(x), blur(y)
    s00, s11, s01 = blur(x * x) - mu0**2, blur(y * y) - mu1**2, blur(x * y) - mu0 * mu1
    smap = (2 * mu0 * mu1 + C1) * (2 * s01 + C2) / ((mu0**2 + mu1**2 + C1) * (s00 + s11 + C2))
    assert ssim_padded(x, y) == pytest.approx(float(smap.mean()), abs=1e-12)
    assert ssim_padded(x, x) == pytest.approx(1.0, abs=1e-12)
    assert abs(ssim_padded(x, y) - ssim(x, y)) > 1e-3  # not DyCheck's 'valid' SSIM


def test_mssim_matches_partial_convolution_loops(rng):
    x = rng.random((16, 18, 3))
    y = np.clip(x + 0.3 * rng.standard_normal(x.shape), 0, 1)
    mask = (rng.random((16, 18)) > 0.4).astype(np.float64)
    mask[:, :6] = 0  # whole empty windows along the width, too
    expected = _brute_ssim(x, y, mask)
    assert mssim(x, y, mask) == pytest.approx(expected, abs=1e-12)
    assert mssim(x, y, mask) != pytest.approx(ssim(x, y), abs=1e-3)


@pytest.mark.parametrize("mask_kind", ["full", "soft", "holes"])
def test_partial_blur_is_the_two_reference_passes_to_the_bit(rng, mask_kind):
    """PartialBlur (the mask's window counts once, identity steps skipped) gives
    what `_partial_blur` along the width, then the height, gives, bit for bit."""
    from mogaf.metrics.image import PartialBlur, _partial_blur

    z = rng.random((17, 23, 3))
    m = {"full": np.ones((17, 23)), "soft": rng.random((17, 23)), "holes": (rng.random((17, 23)) > 0.5) * 1.0}[
        mask_kind
    ]
    if mask_kind == "holes":
        m[:, :12] = 0.0  # windows that hold no mask pixel
    taps = gaussian_window(11, 1.5)
    z1, m1 = _partial_blur(z, m, taps, axis=1)
    expected, _ = _partial_blur(z1, m1, taps, axis=0)
    assert np.array_equal(PartialBlur(m, taps)(z), expected)


def test_cached_reference_statistics_give_the_cold_value_to_the_bit(rng):
    """ssim keeps the ground truth's (second argument's) window statistics by
    content: a cache hit gives the value a cold cache gives, to the bit."""
    from mogaf.metrics.image import REFERENCE_STATISTICS

    gt = rng.random((20, 24, 3))
    mask = (rng.random((20, 24)) > 0.3).astype(np.float64)
    REFERENCE_STATISTICS.clear()
    for _ in range(3):
        pred = rng.random((20, 24, 3))
        cached = (ssim(pred, gt), mssim(pred, gt, mask))
        REFERENCE_STATISTICS.clear()
        assert cached == (ssim(pred, gt), mssim(pred, gt, mask))
    assert len(REFERENCE_STATISTICS.entries) == 2  # one per mask: the full one and `mask`


def test_mssim_full_mask_is_ssim_and_ignores_unmasked_pixels(rng):
    x = rng.random((20, 20, 3))
    y = np.clip(x + 0.1 * rng.standard_normal(x.shape), 0, 1)
    assert mssim(x, y, np.ones((20, 20), bool)) == pytest.approx(ssim(x, y), abs=1e-12)
    mask = np.zeros((20, 20), bool)
    mask[3:15, 5:18] = True
    junk = rng.random(x.shape)
    x2 = np.where(mask[..., None], x, junk)
    y2 = np.where(mask[..., None], y, 1 - junk)
    assert mssim(x2, y2, mask) == pytest.approx(mssim(x, y, mask), abs=1e-12)
    assert mpsnr(x2, y2, mask) == pytest.approx(mpsnr(x, y, mask), abs=1e-9)


def test_mssim_single_pixel_mask_hand_value():
    # One masked pixel at (15, 15) of a 31x31 image: the 11x11 window positions
    # that contain it see only that pixel. Partial convolution rescales the
    # Gaussian tap by n / count = 11 per pass, so there y = 1 blurs to
    # v = 121 g[a] g[b] (a, b: the pixel's offsets in the window) and x = 0 to 0.
    # All other positions see no mask: mu = sigma = 0 and SSIM is exactly 1.
    x = np.zeros((31, 31, 3))
    y = np.ones((31, 31, 3))
    mask = np.zeros((31, 31))
    mask[15, 15] = 1.0
    g = gaussian_window()
    v = 121 * np.outer(g, g)
    s11 = np.maximum(v - v * v, 0)
    inside = C1 * C2 / ((v * v + C1) * (s11 + C2))
    expected = (inside.sum() + (21 * 21 - 121)) / (21 * 21)
    assert mssim(x, y, mask) == pytest.approx(expected, abs=1e-12)
    assert mssim(x, y, mask) == pytest.approx(_brute_ssim(x, y, mask), abs=1e-12)


def test_torch_and_numpy_inputs_agree(rng):
    x = rng.random((16, 16, 3)).astype(np.float32)
    y = rng.random((16, 16, 3)).astype(np.float32)
    m = rng.random((16, 16)) > 0.5
    assert psnr(torch.from_numpy(x), torch.from_numpy(y)) == pytest.approx(psnr(x, y))
    assert mssim(torch.from_numpy(x), y, torch.from_numpy(m)) == pytest.approx(mssim(x, y, m))
