"""The export stage: 3DGS PLY files that render as the evaluation renders.

A small model (dynamic Gaussians moving at constant velocity, a static
background wall) and a forecast of it on the tiny scene's time grid (8 steps,
4 observed) are exported; the files are read back with plyfile and rendered
with mogaf's rasterizer, coloured as 3DGS viewers colour them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from mogaf import stages
from mogaf.artefact import stage_inputs, write_artefact
from mogaf.errors import MogafError
from mogaf.evaluate import images
from mogaf.evaluate.images import render_forecast_views
from mogaf.evaluate.inputs import read_forecast
from mogaf.export.clouds import model_splats, posed_splats, render_splats
from mogaf.export.colors import sphere_quadrature, splat_colors, splat_sh
from mogaf.export.ply import read_splat_ply, splat_property_names, write_splat_ply
from mogaf.rendering import camera_center, render_model
from mogaf.representation import GaussianSet, Model4D, load_model, save_model
from mogaf.sh import gaussian_colors, num_sh_rest
from mogaf.split import load_frames, read_split
from support.paths import REPO
from support.tiny_scene import make_tiny_scene

N_FG, N_BG = 40, 60
OBSERVED, FORECAST = np.arange(4), np.arange(4, 8)  # the tiny scene's split at ratio 0.5
VELOCITY = np.array([0.05, 0.02, 0.0])
# The 3DGS property list of the original code, degree 3 (SuperSplat and the gsplat exporters read this).
THREE_DGS_DEGREE3 = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def _unit(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return q * np.sign(q[..., :1])


def _gaussians(rng: np.random.Generator, means: np.ndarray, scale: float, sh_degree: int) -> GaussianSet:
    n = len(means)
    m = num_sh_rest(sh_degree)
    return GaussianSet(
        means=means.astype(np.float32),
        quats=_unit(rng.normal(size=(n, 4))).astype(np.float32),
        log_scales=np.log(rng.uniform(0.6, 1.4, size=(n, 3)) * scale).astype(np.float32),
        opacity_logits=rng.uniform(0.5, 3.0, size=n).astype(np.float32),
        color_logits=rng.normal(0.0, 1.5, size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(0.0, 0.3, size=(n, m, 3)).astype(np.float32) if m else None,
    )


def _model(sh_degree: int, seed: int = 0) -> Model4D:
    """Dynamic Gaussians near the origin moving at VELOCITY, a background wall at z = 1."""
    rng = np.random.default_rng(seed)
    fg = _gaussians(rng, rng.uniform(-0.3, 0.3, size=(N_FG, 3)), 0.06, sh_degree)
    gy, gx = np.meshgrid(np.linspace(-1.0, 1.0, 6), np.linspace(-1.3, 1.3, 10), indexing="ij")
    wall = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], 1)
    bg = _gaussians(rng, wall, 0.15, sh_degree)
    T = OBSERVED.size
    spin = _unit(fg.quats[:, None] + 0.1 * rng.normal(size=(N_FG, T, 4)))
    return Model4D(
        fg=fg,
        motion_coef_logits=np.zeros((N_FG, 1), np.float32),
        rot6d=np.tile(np.array([1.0, 0, 0, 0, 1, 0], np.float32), (1, T, 1)),
        translations=np.zeros((1, T, 3), np.float32),
        timesteps=OBSERVED,
        trajectory_means=(fg.means[:, None] + VELOCITY * OBSERVED[None, :, None]).astype(np.float32),
        trajectory_quats=spin.astype(np.float32),
        bg=bg,
        sh_degree=sh_degree,
        background=(1.0, 1.0, 1.0),
    )


def _forecast(path: Path, model_h5: Path, split_h5: Path, model: Model4D) -> Path:
    """A constant-velocity forecast of `model`, written as the forecast stage writes one."""
    rng = np.random.default_rng(3)
    means = model.fg.means[:, None] + VELOCITY * FORECAST[None, :, None]
    quats = _unit(model.trajectory_quats[:, -1:] + 0.1 * rng.normal(size=(N_FG, FORECAST.size, 4)))
    with stage_inputs(model_h5, split_h5):  # made from this model, as the forecast stage records it
        return write_artefact(
            path,
            "forecast",
            {
                "timesteps": FORECAST,
                "means": means.astype(np.float32),
                "quats": quats.astype(np.float32),
                "group_id": np.arange(N_FG) % 3,
            },
            config_digest="export-test",
            attrs={"method": "constant_velocity"},
        )


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory) -> tuple[Path, Path]:
    scene_h5, split_h5, _ = make_tiny_scene(tmp_path_factory.mktemp("scene"))
    return scene_h5, split_h5


def _inputs(folder: Path, scene_files, sh_degree: int = 0) -> dict[str, str]:
    scene_h5, split_h5 = scene_files
    model = _model(sh_degree)
    model_h5 = save_model(folder / "refined.h5", "refine", model, config_digest="export-test")
    forecast_h5 = _forecast(folder / "forecast.h5", model_h5, split_h5, model)
    return {"model": str(model_h5), "forecast": str(forecast_h5), "scene": str(scene_h5), "split": str(split_h5)}


def _export(folder: Path, inputs: dict[str, str], **params) -> dict:
    out = folder / "export" / "index.json"
    stages.export(**inputs, out=str(out), params=params)
    return json.loads(out.read_text())


def _render_file(index_json: Path, entry: dict, camera: dict, background) -> np.ndarray:
    splats = read_splat_ply(index_json.parent / entry["file"])
    out = render_splats(splats, camera["K"], camera["w2c"], camera["width"], camera["height"], background)
    return out.features.numpy()


def _ply_header(path: Path) -> str:
    data = path.read_bytes()
    return data[: data.index(b"end_header\n") + len(b"end_header\n")].decode("ascii")


# ---------------------------------------------------------------- (a) round trip
def test_observed_file_renders_as_the_model(tmp_path, scene_files):
    inputs = _inputs(tmp_path, scene_files)
    index = _export(tmp_path, inputs)
    observed = [e for e in index["files"] if e["kind"] == "observed"]
    assert [e["timestep"] for e in observed] == [int(OBSERVED[-1])] and observed[0]["cameras"]
    model = load_model(inputs["model"])
    for camera in observed[0]["cameras"]:
        want = render_model(model, int(OBSERVED[-1]), camera["K"], camera["w2c"], camera["width"], camera["height"])
        got = _render_file(tmp_path / "export" / "index.json", observed[0], camera, model.background)
        assert got.shape == (24, 32, 3) and want.features.std() > 0.05  # a scene with content, not a blank image
        np.testing.assert_allclose(got, want.features.numpy(), atol=2e-5)


def test_degree0_colours_convert_exactly():
    logits = np.random.default_rng(1).normal(0.0, 3.0, size=(500, 3))
    sh_dc, sh_rest = splat_sh(logits, None, 16)
    assert sh_rest.shape == (500, 0, 3)
    got = splat_colors(sh_dc, sh_rest, torch.zeros(500, 3), torch.ones(3)).double().numpy()
    np.testing.assert_allclose(got, 1.0 / (1.0 + np.exp(-logits)), atol=1e-6)


def test_sphere_quadrature_keeps_the_harmonics_orthonormal():
    from mogaf.sh import SH_C0, sh_rest_basis

    dirs, weights = sphere_quadrature(4)  # the fewest nodes export.sh_fit_order allows
    basis = np.concatenate([np.full((len(dirs), 1), SH_C0), sh_rest_basis(torch.from_numpy(dirs), 3).numpy()], 1)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(basis.T @ (weights[:, None] * basis), np.eye(16), atol=1e-12)


# ---------------------------------------------------------------- (b) the 3DGS layout
def test_header_is_the_3dgs_layout(tmp_path, scene_files):
    from plyfile import PlyData

    index = _export(tmp_path, _inputs(tmp_path, scene_files))
    path = tmp_path / "export" / index["files"][0]["file"]
    header = _ply_header(path)
    lines = header.splitlines()
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", f"element vertex {N_FG + N_BG}"]
    degree0 = [n for n in THREE_DGS_DEGREE3 if not n.startswith("f_rest_")]
    assert lines[3:-1] == [f"property float {name}" for name in degree0] and lines[-1] == "end_header"
    ply = PlyData.read(str(path))
    assert ply.byte_order == "<" and not ply.text and [e.name for e in ply.elements] == ["vertex"]
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == splat_property_names(0) == degree0
    assert all(vertex.data.dtype[name] == np.dtype("<f4") for name in degree0)
    assert not np.any(vertex.data["nx"]) and not np.any(vertex.data["ny"]) and not np.any(vertex.data["nz"])
    # the file size is the header and one record of float32s per Gaussian: nothing else in it
    assert path.stat().st_size == len(header) + (N_FG + N_BG) * 4 * len(degree0)


def test_ply_holds_the_gaussians_parameters_as_3dgs_stores_them(tmp_path, scene_files):
    from plyfile import PlyData

    inputs = _inputs(tmp_path, scene_files, sh_degree=3)
    index = _export(tmp_path, inputs)
    model = load_model(inputs["model"])
    data = PlyData.read(str(tmp_path / "export" / index["files"][0]["file"]))["vertex"].data
    fg, bg = model.fg, model.bg
    xyz = np.stack([data[k] for k in ("x", "y", "z")], 1)
    np.testing.assert_array_equal(xyz[:N_FG], model.trajectory_means[:, -1])
    np.testing.assert_array_equal(xyz[N_FG:], bg.means)
    rot = np.stack([data[f"rot_{i}"] for i in range(4)], 1)  # w, x, y, z
    np.testing.assert_array_equal(rot, np.concatenate([model.trajectory_quats[:, -1], bg.quats]))
    scales = np.stack([data[f"scale_{i}"] for i in range(3)], 1)
    np.testing.assert_array_equal(scales, np.concatenate([fg.log_scales, bg.log_scales]))
    np.testing.assert_array_equal(data["opacity"], np.concatenate([fg.opacity_logits, bg.opacity_logits]))
    # f_rest channel-major: every coefficient of R, then of G, then of B
    rest = np.stack([data[f"f_rest_{i}"] for i in range(45)], 1).reshape(-1, 3, 15)
    _, fitted = splat_sh(fg.color_logits, fg.sh_rest, 16)
    np.testing.assert_allclose(rest[:N_FG], fitted.transpose(0, 2, 1), rtol=1e-6, atol=1e-7)


# ---------------------------------------------------------------- (c) SH degrees 0 and 3
@pytest.mark.parametrize("sh_degree", [0, 3])
def test_sh_degrees_export_and_render(tmp_path, scene_files, sh_degree):
    inputs = _inputs(tmp_path, scene_files, sh_degree)
    index = _export(tmp_path, inputs)
    assert index["sh_degree"] == sh_degree and index["sh_colors"] == ("exact" if sh_degree == 0 else "fitted")
    path = tmp_path / "export" / index["files"][0]["file"]
    rest = [line for line in _ply_header(path).splitlines() if line.startswith("property float f_rest_")]
    assert len(rest) == {0: 0, 3: 45}[sh_degree]
    if sh_degree == 3:
        assert splat_property_names(3) == THREE_DGS_DEGREE3
    splats = read_splat_ply(path)
    assert splats.sh_degree == sh_degree and splats.sh_rest.shape == (N_FG + N_BG, num_sh_rest(sh_degree), 3)
    model = load_model(inputs["model"])
    entry = index["files"][0]
    for camera in entry["cameras"]:
        want = render_model(model, entry["timestep"], camera["K"], camera["w2c"], camera["width"], camera["height"])
        got = _render_file(tmp_path / "export" / "index.json", entry, camera, model.background)
        error = np.abs(got - want.features.numpy())
        if sh_degree == 0:
            assert error.max() < 2e-5
        else:  # the least-squares fit of a sigmoid colour: close, not exact
            assert error.max() < 0.02 and error.mean() < 2e-3, (error.max(), error.mean())


def test_degree3_fit_is_close_over_every_view_direction():
    rng = np.random.default_rng(2)
    g = _gaussians(rng, rng.normal(size=(300, 3)), 0.1, 3)
    sh_dc, sh_rest = splat_sh(g.color_logits, g.sh_rest, 16)
    errors = []
    for cam in rng.normal(size=(20, 3)) * 10:
        cam_t = torch.tensor(cam, dtype=torch.float32)
        means = torch.tensor(g.means)
        want = gaussian_colors(torch.tensor(g.color_logits), torch.tensor(g.sh_rest), means, cam_t)
        errors.append((splat_colors(sh_dc, sh_rest, means, cam_t) - want).abs().numpy())
    # view-dependent offsets of about +-0.5 in logit (sh_rest ~ N(0, 0.3)): a few 1e-3 on average
    assert np.max(errors) < 0.05 and np.mean(errors) < 3e-3, (np.max(errors), np.mean(errors))
    # without view dependence the fit is the exact conversion
    dc_only, rest_zero = splat_sh(g.color_logits, np.zeros_like(g.sh_rest), 16)
    np.testing.assert_allclose(dc_only, splat_sh(g.color_logits, None, 16)[0], atol=1e-12)
    assert np.abs(rest_zero).max() < 1e-12


# ---------------------------------------------------------------- (d) group ids
def test_groupwise_export_adds_group_id_last(tmp_path, scene_files):
    from plyfile import PlyData

    inputs = _inputs(tmp_path, scene_files)
    index = _export(tmp_path, inputs, group_id=True)
    assert index["group_id"] is True
    for entry in index["files"]:
        path = tmp_path / "export" / entry["file"]
        lines = _ply_header(path).splitlines()
        assert lines[-2:] == ["property int group_id", "end_header"]
        vertex = PlyData.read(str(path))["vertex"]
        assert [p.name for p in vertex.properties] == [*splat_property_names(0), "group_id"]
        assert vertex.data.dtype["group_id"] == np.dtype("<i4")
        np.testing.assert_array_equal(vertex.data["group_id"][:N_FG], np.arange(N_FG) % 3)
        assert np.all(vertex.data["group_id"][N_FG:] == -1)  # the static background
        assert read_splat_ply(path).group_id is not None
    # the same Gaussians as without group ids
    plain = model_splats(load_model(inputs["model"]), quadrature_order=16)
    assert plain.group_id is None
    with_ids = read_splat_ply(tmp_path / "export" / index["files"][1]["file"])
    np.testing.assert_array_equal(with_ids.log_scales, plain.log_scales)


# ---------------------------------------------------------------- (e) forecast steps
def test_forecast_files_render_as_the_evaluation_does(tmp_path, scene_files):
    inputs = _inputs(tmp_path, scene_files)
    index = _export(tmp_path, inputs)
    split = read_split(inputs["split"])
    forecasts = [e for e in index["files"] if e["kind"] == "forecast"]
    assert [e["timestep"] for e in forecasts] == FORECAST.tolist()
    assert [e["time"] for e in forecasts] == pytest.approx((FORECAST / (split.num_timesteps - 1)).tolist())
    assert index["method"] == "constant_velocity" and index["num_gaussians"] == {"dynamic": N_FG, "background": N_BG}
    model = load_model(inputs["model"])
    frames = load_frames(inputs["scene"], split, "evaluation")
    want = render_forecast_views(model, read_forecast(inputs["forecast"]), frames, {})
    rendered = 0
    for entry in forecasts:
        for camera in entry["cameras"]:
            f = frames.frame_names.index(camera["frame"])
            assert int(frames.time_index[f]) == entry["timestep"]
            np.testing.assert_array_equal(camera["K"], frames.K[f])
            np.testing.assert_array_equal(camera["w2c"], frames.w2c[f])
            assert (camera["width"], camera["height"]) == (frames.width, frames.height)
            got = _render_file(tmp_path / "export" / "index.json", entry, camera, model.background)
            np.testing.assert_allclose(np.clip(got, 0.0, 1.0), want[f], atol=2e-5)
            rendered += 1
    assert rendered == frames.num_frames  # every evaluation view


def test_same_poses_as_before_finds_runs_of_equal_steps():
    means = np.zeros((3, 5, 3))
    means[:, 1] = 1.0  # moves at step 1, then stops there
    means[:, 2:] = 1.0
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (3, 5, 1))
    np.testing.assert_array_equal(images.same_poses_as_before(means, quats), [0, 1, 1, 1, 1])
    quats[0, 3] = [0.0, 1.0, 0.0, 0.0]  # turns at step 3 (and back at 4)
    np.testing.assert_array_equal(images.same_poses_as_before(means, quats), [0, 1, 1, 3, 4])


def test_a_frozen_forecast_is_rendered_once_per_camera_as_every_frame_alone(tmp_path, scene_files, monkeypatch):
    """Evaluation frames with the same camera and the same poses share one
    render, which is the image each of them gives rendered alone; a moving
    forecast renders every frame."""
    inputs = _inputs(tmp_path, scene_files)
    model = load_model(inputs["model"])
    frames = load_frames(inputs["scene"], read_split(inputs["split"]), "evaluation")
    moving = read_forecast(inputs["forecast"])
    n = moving["timesteps"].size
    frozen = {
        **moving,
        "means": np.repeat(moving["means"][:, :1], n, 1),
        "quats": np.repeat(moving["quats"][:, :1], n, 1),
    }
    cameras = {(frames.K[f].tobytes(), frames.w2c[f].tobytes()) for f in range(frames.num_frames)}
    assert len(cameras) < frames.num_frames  # fixed evaluation views, seen at several times
    render = images.render_poses
    calls = []
    monkeypatch.setattr(images, "render_poses", lambda *a: (calls.append(1), render(*a))[1])
    shared = render_forecast_views(model, frozen, frames, {})
    assert len(calls) == len(cameras)
    for f in range(frames.num_frames):
        alone = render(
            model, frozen["means"][:, 0], frozen["quats"][:, 0], frames.K[f], frames.w2c[f], frames.width, frames.height
        )
        np.testing.assert_array_equal(shared[f], np.clip(alone.features[..., :3].numpy().astype(np.float64), 0.0, 1.0))
    calls.clear()
    render_forecast_views(model, moving, frames, {})
    assert len(calls) == frames.num_frames


def test_steps_pick_the_forecast_files(tmp_path, scene_files):
    inputs = _inputs(tmp_path, scene_files)
    index = _export(tmp_path, inputs, steps=[7, 5])
    assert [(e["kind"], e["timestep"]) for e in index["files"]] == [("observed", 3), ("forecast", 5), ("forecast", 7)]
    assert sorted(p.name for p in (tmp_path / "export" / "ply").iterdir()) == [
        "forecast_t0005.ply",
        "forecast_t0007.ply",
        "observed_t0003.ply",
    ]
    with pytest.raises(MogafError, match=r"export param 'steps': 2 is not a forecast time step of .*forecast.h5"):
        _export(tmp_path / "again", inputs, steps=[2])


def test_posed_splats_move_only_the_dynamic_rows():
    model = _model(0)
    splats = model_splats(model, quadrature_order=16)
    moved = posed_splats(splats, model.trajectory_means[:, 2], model.trajectory_quats[:, 2])
    np.testing.assert_array_equal(moved.means[:N_FG], model.trajectory_means[:, 2])
    np.testing.assert_array_equal(moved.means[N_FG:], splats.means[N_FG:])
    np.testing.assert_array_equal(splats.means[:N_FG], model.fg.means)  # the template is left as it was
    cam = camera_center(torch.eye(4))
    assert splat_colors(moved.sh_dc, moved.sh_rest, torch.tensor(moved.means), cam).shape == (N_FG + N_BG, 3)


# ---------------------------------------------------------------- (f) bad input
def test_missing_input_is_one_line_naming_it(tmp_path, scene_files):
    inputs = _inputs(tmp_path, scene_files)
    missing = str(tmp_path / "nope.h5")
    out = tmp_path / "export" / "index.json"
    for role in ("model", "forecast"):
        with pytest.raises(MogafError) as err:
            stages.export(**{**inputs, role: missing}, out=str(out), params={})
        assert str(err.value).startswith(f"{missing}: missing") and "\n" not in str(err.value)
    assert not out.parent.exists()  # nothing written


def test_a_forecast_of_another_model_or_an_output_over_an_input_is_refused(tmp_path, scene_files):
    inputs = _inputs(tmp_path / "a", scene_files)
    other = _inputs(tmp_path / "b", scene_files, sh_degree=3)  # another reconstruction of the scene
    out = tmp_path / "export" / "index.json"
    with pytest.raises(
        MogafError, match=r"b/forecast\.h5: was made from another 'refine' artefact than .*a/refined\.h5"
    ):
        stages.export(**{**inputs, "forecast": other["forecast"]}, out=str(out), params={})
    with pytest.raises(MogafError, match=r"forecast\.h5: is also an input of this stage"):
        stages.export(**inputs, out=inputs["forecast"], params={})
    assert not out.parent.exists()


def test_cli_export_writes_the_files_and_reports_a_missing_one_in_one_line(tmp_path, scene_files, monkeypatch, capsys):
    from mogaf import cli

    monkeypatch.chdir(REPO)  # the CLI finds config/ relative to the working folder, as the workflow does
    inputs = _inputs(tmp_path, scene_files)
    out = tmp_path / "cli" / "index.json"
    paths = ["--forecast-h5", inputs["forecast"], "--scene-h5", inputs["scene"], "--split-h5", inputs["split"]]
    assert cli.main(["export", "--model-h5", inputs["model"], *paths, "--out", str(out)]) == 0
    files = [e["file"] for e in json.loads(out.read_text())["files"]]
    assert len(files) == 1 + FORECAST.size and all((out.parent / f).is_file() for f in files)
    capsys.readouterr()  # the run's log lines
    missing = str(tmp_path / "gone" / "refined.h5")
    with pytest.raises(SystemExit) as exc:
        cli.main(["export", "--model-h5", missing, *paths, "--out", str(tmp_path / "cli2" / "index.json")])
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"mogaf: error: {missing}: missing") and "\n" not in err


def test_a_damaged_ply_is_one_line_naming_it(tmp_path):
    model = _model(0)
    path = write_splat_ply(tmp_path / "a.ply", model_splats(model, quadrature_order=16))
    data = path.read_bytes()
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(data[: len(data) - 100])
    other = tmp_path / "other.ply"
    other.write_bytes(data.replace(b"property float opacity\n", b"property float alpha__\n"))
    for bad, why in (
        (truncated, "not a readable PLY file"),
        (other, "not the 3DGS layout"),
        (tmp_path / "no.ply", "missing"),
    ):
        with pytest.raises(MogafError) as err:
            read_splat_ply(bad)
        assert str(err.value).startswith(f"{bad}: ") and why in str(err.value) and "\n" not in str(err.value)
