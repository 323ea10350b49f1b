"""Group-wise refinement on the tiny rendered scene of support.tiny_scene."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from mogaf.errors import MogafError
from mogaf.grouping.core import Groups
from mogaf.grouping.stage import load_groups, run_rigid_init_stage, write_groups
from mogaf.recon.stage import run_recon_stage
from mogaf.refine import resolve_params
from mogaf.refine.stage import run_refine_stage
from mogaf.refine.trainer import neighbour_pairs, rigid_residuals
from mogaf.representation import load_model
from support.tiny_scene import TINY_PARAMS, assert_same_arrays, differs, make_tiny_scene, perturbed_checkpoint

REFINE = {"iterations": 40, "rigid_times": 2, "recon": {"checkpoint_every": 10}}


def _groups(n: int, *, rigid: int, static: int = 0) -> Groups:
    return Groups(
        group_id=np.zeros(n, np.int64),
        rigid=np.array([rigid], np.int8),
        static=np.array([static], np.int8),
        instance_id=np.array([1]),
        names=["cluster"],
        rigid_source=["config"],
        method="test",
        params={},
    )


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("refine")
    scene, split, priors = make_tiny_scene(folder)
    recon = run_recon_stage(scene, split, priors, folder / "recon.h5", TINY_PARAMS, seed=0, progress=False)
    n = len(load_model(recon).fg)
    rigid_groups = write_groups(folder / "groups_rigid.h5", _groups(n, rigid=1))
    nr_groups = write_groups(folder / "groups_nr.h5", _groups(n, rigid=0))
    rigid = run_rigid_init_stage(recon, rigid_groups, folder / "rigid.h5", {})
    return {
        "folder": folder,
        "scene": scene,
        "split": split,
        "priors": priors,
        "recon": recon,
        "rigid_groups": rigid_groups,
        "nr_groups": nr_groups,
        "rigid": rigid,
    }


def _refine(t, out, groups="rigid_groups", rigid="rigid", params=REFINE, **kw):
    return run_refine_stage(
        t["recon"],
        t[groups],
        t[rigid] if rigid else None,
        t["priors"],
        t["scene"],
        t["split"],
        t["folder"] / out,
        params,
        seed=0,
        progress=False,
        **kw,
    )


def test_rigid_group_residual_drops_and_schema_matches_recon(tiny):
    path = _refine(tiny, "refined_rigid.h5")
    recon, refined = load_model(tiny["recon"]), load_model(path, ("refine",))
    assert refined.trajectory_means.shape == recon.trajectory_means.shape
    assert refined.groups["group_id"].shape == (len(recon.fg),)
    assert refined.groups["group_rigid"].tolist() == [1]
    groups = load_groups(tiny["rigid_groups"])
    before, after = rigid_residuals(recon, groups), rigid_residuals(refined, groups)
    assert after["0"] < before["0"], (before, after)
    assert refined.attrs["rigid_residual_after"]["0"] == pytest.approx(after["0"])
    assert np.isfinite(refined.trajectory_means).all()


def test_nonrigid_group_needs_no_rigid_file_and_smooths_coefficients(tiny):
    path = _refine(tiny, "refined_nr.h5", groups="nr_groups", rigid=None, params={**REFINE, "lambda_nr": 1.0})
    recon, refined = load_model(tiny["recon"]), load_model(path, ("refine",))
    groups = load_groups(tiny["nr_groups"])
    pairs = neighbour_pairs(recon.fg.means, groups, 8, 3.0)[0]

    def roughness(m):
        w = m.motion_coefs()
        return float(((w[pairs[:, 0]] - w[pairs[:, 1]]) ** 2).sum(-1).mean())

    assert roughness(refined) < roughness(recon)
    assert refined.attrs["num_nr_pairs"] == len(pairs)


def test_static_scene_is_a_noop(tiny):
    n = len(load_model(tiny["recon"]).fg)
    static = write_groups(tiny["folder"] / "groups_static.h5", _groups(n, rigid=1, static=1))
    out = run_refine_stage(
        tiny["recon"],
        static,
        None,
        tiny["priors"],
        tiny["scene"],
        tiny["split"],
        tiny["folder"] / "refined_static.h5",
        REFINE,
        seed=0,
        progress=False,
    )
    recon, refined = load_model(tiny["recon"]), load_model(out, ("refine",))
    assert refined.attrs["noop"] == 1
    np.testing.assert_array_equal(refined.trajectory_means, recon.trajectory_means)
    np.testing.assert_array_equal(refined.fg.means, recon.fg.means)


def test_rigid_groups_without_rigid_file_fail_clearly(tiny):
    with pytest.raises(MogafError, match="rigid_init"):
        _refine(tiny, "never.h5", rigid=None)
    assert not (tiny["folder"] / "never.h5").exists()


def test_resume_and_determinism(tiny, caplog):
    a = _refine(tiny, "a.h5")
    ck = tiny["folder"] / "refine.pt"
    assert _refine(tiny, "b.h5", checkpoint=ck, stop_at=15) == ck and ck.exists()
    assert not (tiny["folder"] / "b.h5").exists()
    moved = tiny["folder"] / "moved.pt"
    perturbed_checkpoint(ck, moved)
    with caplog.at_level(logging.INFO, logger="mogaf"):
        b = _refine(tiny, "b.h5", checkpoint=ck)
    assert f"refine: resumed from {ck} at iteration 15" in caplog.text
    assert not ck.exists()
    assert_same_arrays(a, b)
    assert differs(b, _refine(tiny, "moved.h5", checkpoint=moved))  # the state is read, not recomputed


def test_params_are_checked():
    with pytest.raises(MogafError, match="refine: unknown parameter"):
        resolve_params({"lambda": 1})
    with pytest.raises(MogafError, match="lambda_rigid"):
        resolve_params({"lambda_rigid": -1})
    p = resolve_params({}, {"iterations": 9999, "downscale": 2})
    assert p["recon"]["downscale"] == 2 and p["recon"]["iterations"] == p["iterations"]
    assert p["recon"]["stop_control_fraction"] == 0.0
