"""Shared pieces of the forecasters: the result type, the base class, input
checks, parameter merging and the determinism context."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from mogaf.devices import check_device_name, resolve_device
from mogaf.errors import MogafError, refuse_unknown_params
from mogaf.forecast import quat
from mogaf.forecast.params import METHOD_SETTINGS
from mogaf.settings import check

POSE_DIM = 7  # [mu (3), q (4, wxyz)]


@dataclasses.dataclass
class ForecastResult:
    """Poses at the next n_steps timesteps and what happened while fitting.

    poses: (G, n_steps, 7) float64, unit quaternions (wxyz) whose signs follow
        continuity from the (sign-canonicalised) observation.
    info: train_time_s, rollout_time_s, final_loss, epochs, iterations, and
        method-specific flags (e.g. ode_step_cap_hit).
    bodies: Forecaster.bodies(), or None.
    """

    poses: np.ndarray
    info: dict[str, Any]
    bodies: np.ndarray | None = None


def merge_params(method: str, defaults: Mapping[str, Any], params: Mapping[str, Any] | None) -> dict[str, Any]:
    """`defaults` updated with params, each checked against the method's
    settings (mogaf.forecast.params.METHOD_SETTINGS); unknown keys are a one-line MogafError."""
    cls = METHOD_SETTINGS.get(method)
    if cls is None:  # a method without settings
        if params is not None and not isinstance(params, Mapping):
            raise MogafError(f"forecast.{method}: params must be a mapping, got {type(params).__name__}")
        refuse_unknown_params(f"forecast.{method}", params or {}, defaults)
        return {**defaults, **dict(params or {})}
    return check(cls, f"forecast.{method}", params, base=defaults)


def check_observed(observed: Any, method: str, min_frames: int) -> np.ndarray:
    """Validate (G, T, 7), finite, non-zero quaternions; return a float64 copy
    with unit, sign-continuous quaternions (see quat.make_continuous)."""
    try:
        arr = np.array(observed, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MogafError(f"forecast.{method}: observed is not a numeric array ({exc})") from None
    if arr.ndim != 3 or arr.shape[2] != POSE_DIM:
        raise MogafError(f"forecast.{method}: observed must have shape (G, T, 7), got {arr.shape}")
    g, t, _ = arr.shape
    if g < 1:
        raise MogafError(f"forecast.{method}: observed holds no Gaussians")
    if t < min_frames:
        raise MogafError(f"forecast.{method}: needs at least {min_frames} observed frames, got {t}")
    if not np.isfinite(arr).all():
        raise MogafError(f"forecast.{method}: observed contains NaN or infinite values")
    norms = np.linalg.norm(arr[..., 3:], axis=-1)
    if (norms < 1e-8).any():
        raise MogafError(f"forecast.{method}: observed contains zero-length quaternions")
    arr[..., 3:] = quat.make_continuous(arr[..., 3:] / norms[..., None], axis=1)
    return arr


def check_steps(n_steps: Any, method: str) -> int:
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
        raise MogafError(f"forecast.{method}: n_steps must be a positive integer, got {n_steps!r}")
    return int(n_steps)


def epochs_for(epochs: int, steps: int, steps_per_epoch: int) -> int:
    """Epochs of a baseline's training: its papers' `epochs` when `steps` is 0,
    else the fewest whole epochs giving at least `steps` optimiser steps (a
    paper's epoch is a pass over a whole scene; a group's is far shorter or
    longer, so a step budget is what compares across groups)."""
    if steps <= 0:
        return epochs
    return max(1, -(-steps // max(steps_per_epoch, 1)))


def finish_poses(poses: np.ndarray, last_q: np.ndarray) -> np.ndarray:
    """Float64 copy with unit quaternions, sign-continuous from last_q (G, 4)."""
    out = np.array(poses, dtype=np.float64, copy=True)
    q = quat.normalize(out[..., 3:])
    prev = last_q
    for k in range(q.shape[1]):
        q[:, k] = quat.align_to(q[:, k], prev)
        prev = q[:, k]
    out[..., 3:] = q
    return out


# torch's NaN fill of new tensors under deterministic mode (torch_determinism)
FILL_UNINITIALIZED_MEMORY = False


@contextlib.contextmanager
def torch_determinism(seed: int, num_threads: int | None, device: Any = None) -> Iterator[None]:
    """Seed torch inside a forked RNG state (the caller's global RNG is left as
    it was), optionally pin the intra-op thread count, and ask for
    deterministic kernels. Restores everything on exit. `device`: the torch
    device the caller computes on; a CUDA one's generator is forked too (only
    that one: forking every visible GPU would open a context on each).

    Deterministic mode's other switch, torch's NaN fill of every new tensor
    (torch.utils.deterministic.fill_uninitialized_memory, a guard against
    kernels reading memory nobody wrote), is off inside: the forecasters'
    kernels write all they read, so their results are the same bits either
    way (tests/test_forecast.py), and the fill costs time on large
    tensors (a tenth of a 3,000-Gaussian group's GCN training)."""
    import torch
    import torch.utils.deterministic

    from mogaf.optim import use_deterministic_algorithms

    old_threads = torch.get_num_threads()
    old_det = torch.are_deterministic_algorithms_enabled()
    old_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    old_fill = torch.utils.deterministic.fill_uninitialized_memory
    dev = torch.device(device) if device is not None else torch.device("cpu")
    cuda_devices = [dev.index if dev.index is not None else torch.cuda.current_device()] if dev.type == "cuda" else []
    with torch.random.fork_rng(devices=cuda_devices):
        torch.manual_seed(int(seed))
        if num_threads:
            torch.set_num_threads(int(num_threads))
        use_deterministic_algorithms(True, warn_only=True)
        torch.utils.deterministic.fill_uninitialized_memory = FILL_UNINITIALIZED_MEMORY
        try:
            yield
        finally:
            torch.utils.deterministic.fill_uninitialized_memory = old_fill
            use_deterministic_algorithms(old_det, warn_only=old_warn)
            torch.set_num_threads(old_threads)


def flushing_denormals() -> bool:
    """Whether this thread's CPU arithmetic reads and writes subnormal floats
    as zero (torch.set_flush_denormal has no getter: a subnormal times one)."""
    import torch

    return float(torch.tensor([1e-39]) * 1.0) == 0.0


@contextlib.contextmanager
def flush_denormals(device: Any = None) -> Iterator[None]:
    """Subnormal floats (|x| < 1.2e-38 in float32) read and written as zero by
    this thread's CPU arithmetic inside the block (x86 FTZ/DAZ; a no-op where
    the CPU has no such mode, and on CUDA). Attention on tiny heads produces
    such values once its softmax sharpens, and Intel CPUs take each of them
    through a microcode path about a hundred times slower; a value that small
    is below the rounding of any sum with a normal-sized term (tested on the
    paper's network). The caller's mode is restored on exit."""
    import torch

    on_cpu = device is None or torch.device(device).type == "cpu"
    # switched on here only where it was off and the CPU has the mode: only then switched off again
    if on_cpu and not flushing_denormals() and torch.set_flush_denormal(True):
        try:
            yield
        finally:
            torch.set_flush_denormal(False)
    else:
        yield


class Forecaster:
    """A forecaster of one group: settings loaded once (load_settings, or
    given already loaded), then fit(observed, rigid, horizon), then
    rollout(n_steps). Subclasses set NAME, DEFAULTS, MIN_FRAMES (and
    NEEDS_HORIZON) and implement _fit / _rollout on the checked float64 array."""

    NAME = "base"
    DEFAULTS: Mapping[str, Any] = {}
    MIN_FRAMES = 1
    # The fit depends on the forecast's length (MoGaF's structured mode: the
    # backtest holds back at most the horizon): fit(horizon=) is required.
    NEEDS_HORIZON = False

    @classmethod
    def load_settings(cls, params: Any) -> Any:
        """The typed settings this forecaster reads (its class in
        mogaf.forecast.params.METHOD_SETTINGS; None for a method without
        settings): `params` (a mapping) over DEFAULTS, each checked once.
        Settings already loaded are returned as they are."""
        settings_cls = METHOD_SETTINGS.get(cls.NAME)
        if settings_cls is not None and isinstance(params, settings_cls):
            return params
        merged = merge_params(cls.NAME, cls.DEFAULTS, params)
        return settings_cls(**merged) if settings_cls is not None else None

    @classmethod
    def for_settings(cls, settings: Any) -> type[Forecaster]:
        """The class that runs these (loaded) settings: this one, unless a
        setting picks another (MoGaF's mode)."""
        return cls

    def __init__(self, params: Any = None, seed: int = 0, device: str = "cpu"):
        """`params`: a mapping over DEFAULTS, or the settings load_settings returned."""
        self.settings = self.load_settings(params)  # what the method reads (None for a method without settings)
        picked = self.for_settings(self.settings)
        if picked is not type(self):
            raise MogafError(
                f"forecast.{self.NAME}: these settings are run by {picked.__name__}, not {type(self).__name__} "
                "(make_forecaster picks the class)"
            )
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise MogafError(f"forecast.{self.NAME}: seed must be an integer, got {seed!r}")
        self.seed = int(seed)
        # Where the torch-based methods train and roll out ("auto": CUDA when
        # torch sees it); resolved when first needed, so classical methods never import torch.
        self.device_name = check_device_name(device, f"forecast.{self.NAME}")
        self._device = None
        self.info: dict[str, Any] = {"method": self.NAME}
        self._obs: np.ndarray | None = None
        self.rigid_hint: bool | None = None
        self.horizon: int | None = None

    def fit(self, observed: np.ndarray, rigid: bool | None = None, horizon: int | None = None) -> Forecaster:
        """`rigid`: whether the group moves rigidly (the grouping's flag), None
        when unknown; methods without a notion of groups ignore it. `horizon`:
        the steps the forecast will roll out (rollout then takes exactly
        that many); required where NEEDS_HORIZON, optional elsewhere."""
        obs = check_observed(observed, self.NAME, self.MIN_FRAMES)
        if horizon is not None:
            horizon = check_steps(horizon, self.NAME)
        elif self.NEEDS_HORIZON:
            raise MogafError(
                f"forecast.{self.NAME}: fit needs the forecast horizon (fit(observed, horizon=n_steps)): "
                "its fit depends on the forecast's length"
            )
        self._obs = obs
        self.rigid_hint = rigid
        self.horizon = horizon
        t0 = time.perf_counter()
        self._fit(obs)
        self.info["train_time_s"] = time.perf_counter() - t0
        self.info.setdefault("final_loss", None)
        self.info.setdefault("epochs", 0)
        return self

    def bodies(self) -> np.ndarray | None:
        """(G,) which rigid body the fitted forecast moves each member with
        (labels from 0; -1: a member moved on its own), or None where the
        method has no such notion."""
        return None

    def rollout(self, n_steps: int) -> np.ndarray:
        """(G, n_steps, 7) poses after the observed ones; n_steps: the fit's
        horizon where one was given."""
        if self._obs is None:
            raise MogafError(f"forecast.{self.NAME}: rollout called before fit")
        n = check_steps(n_steps, self.NAME)
        if self.horizon is not None and n != self.horizon:
            raise MogafError(
                f"forecast.{self.NAME}: fitted for a {self.horizon}-step forecast, asked for {n} steps (fit again)"
            )
        t0 = time.perf_counter()
        poses = self._rollout(n)
        poses = finish_poses(poses, self._obs[:, -1, 3:])
        self.info["rollout_time_s"] = time.perf_counter() - t0
        if not np.isfinite(poses).all():
            # Never hand out NaNs: this is a bug or an unrecoverable blow-up.
            raise MogafError(f"forecast.{self.NAME}: rollout produced non-finite poses")
        return poses

    @property
    def device(self):
        """The torch device of this forecaster's tensors (recorded in info)."""
        if self._device is None:
            self._device = resolve_device(self.device_name, f"forecast.{self.NAME}")
            self.info["device"] = self._device.type
        return self._device

    def _fit(self, obs: np.ndarray) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _rollout(self, n_steps: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError
