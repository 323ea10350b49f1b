"""Bad inputs and faults that used to get through: a full disk, an
output that is an input or lies in a dataset folder, degenerate datasets,
bad metrics.json files, config and name errors, a read-only results folder
and malformed artefacts. Each gives one line naming the file (exit status 1),
or a warning where the data is usable, and loses or overwrites nothing.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from mogaf import cli, stages
from mogaf.artefact import atomic, write_artefact, write_json
from mogaf.artefact.header import ATTR_CHECKSUM, dataset_checksum
from mogaf.datasets import read_scene
from mogaf.datasets.common import DatasetWarning
from mogaf.errors import MogafError
from mogaf.grouping.core import Groups
from mogaf.grouping.stage import write_groups
from mogaf.paths import check_outputs, unwritable_folder
from mogaf.report import load_metrics
from mogaf.representation import GaussianSet, Model4D, save_model
from mogaf.schema import config_error, load_config_schema
from mogaf.split import split_scene
from support.fake_datasets import fake_dnerf, write_png
from support.fake_datasets import write_json as write_dataset_json
from support.paths import REPO

# about 28 s with two workers: collected early (tests/conftest.py)
pytestmark = pytest.mark.long(seconds=28)

CONFIG = REPO / "config" / "config.yaml"
SCHEMA = load_config_schema(REPO / "config" / "schema.yaml")


@pytest.fixture(autouse=True)
def _root_log_handlers(restore_root_logging):
    """Every test here may run a stage through run_stage (tests/conftest.py)."""


@pytest.fixture
def in_repo(monkeypatch):
    monkeypatch.chdir(REPO)  # the CLI finds config/ relative to the working folder, as the workflow does


def _one_line(text: str) -> str:
    assert text.startswith("mogaf: error: ") and "\n" not in text, text
    return text


def _cli_error(capsys, *argv: str) -> str:
    """Run the CLI in-process: exit status 1 and one `mogaf: error:` line."""
    with pytest.raises(SystemExit) as exc:
        raise SystemExit(cli.main(list(argv)))
    assert exc.value.code == 1
    return _one_line(capsys.readouterr().err.strip())


def _fails(fn, *args, **kwargs) -> str:
    with pytest.raises(MogafError) as exc:
        fn(*args, **kwargs)
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def _dnerf_config(tmp_path: Path, folder: Path) -> str:
    """config/config.yaml plus a dataset 'fk' of D-NeRF layout at `folder`."""
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["datasets"]["fk"] = {"layout": "dnerf", "path": str(folder.parent / "{scene}"), "scenes": [folder.name]}
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    write_dataset_json(path, data)


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A small D-NeRF scene, read-only for the tests (copy it to change it)."""
    return fake_dnerf(tmp_path_factory.mktemp("data") / "s", counts={"train": 6, "test": 4})


@pytest.fixture
def scene_copy(dataset, tmp_path) -> Path:
    return Path(shutil.copytree(dataset, tmp_path / "data" / "s"))


@pytest.fixture(scope="module")
def scene_h5(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene") / "scene.h5"
    stages.ingest(str(dataset), str(out), "dnerf", {}, "fk", "s")
    return out


# ---------------------------------------------------------------- full disk
def _mount_tmpfs(folder: Path, size: str) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    folder.mkdir(parents=True, exist_ok=True)
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True)
    return res.returncode == 0


@pytest.fixture
def nearly_full_disk(tmp_path):
    """A 1 MiB tmpfs with about 48 KiB left (needs root and mount rights)."""
    folder = tmp_path / "fulldisk"
    if not _mount_tmpfs(folder, "1m"):
        pytest.skip("mounting a small tmpfs is not permitted here (needs root); the injected-failure tests cover it")
    try:
        (folder / "filler").write_bytes(b"\0" * (1024 * 1024 - 48 * 1024))
        yield folder
    finally:
        # a file still open in it (a failing test's) keeps it busy: then detach it lazily
        if subprocess.run(["umount", str(folder)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(folder)], check=False)


def test_full_disk_real_tmpfs_one_line_no_temp(nearly_full_disk, tmp_path):
    # In a child process: h5py used to segfault here (exit 139) after 55 lines of tracebacks.
    big = fake_dnerf(tmp_path / "big" / "s", counts={"train": 10, "test": 6}, size=128, ply=None)  # ~150 KB
    configfile = _dnerf_config(tmp_path, big)
    out = nearly_full_disk / "scene.h5"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "mogaf",
            "ingest",
            "--folder",
            str(big),
            "--out",
            str(out),
            "--layout",
            "dnerf",
            "--dataset",
            "fk",
            "--scene",
            "s",
            "--configfile",
            configfile,
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 1, res.stderr[-2000:]
    errors = [line for line in res.stderr.splitlines() if " INFO " not in line]
    assert len(errors) == 1, res.stderr[-2000:]
    assert errors[0].startswith(f"mogaf: error: {out}: cannot be written: no space left on device")
    assert sorted(p.name for p in nearly_full_disk.iterdir()) == ["filler"]  # no artefact, no hidden temporary


def _pwrite_failing_after(limit: int):
    """os.pwrite that hits a full disk once `limit` bytes are written."""
    real = os.pwrite
    written = [0]

    def pwrite(fd, data, offset):
        if written[0] + len(data) > limit:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written[0] += len(data)
        return real(fd, data, offset)

    return pwrite


def test_full_disk_inside_the_hdf5_write_is_one_line_and_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(os, "pwrite", _pwrite_failing_after(20_000))
    out = tmp_path / "a.h5"
    data = {"x": np.random.default_rng(0).integers(0, 255, (40, 64, 64, 3), dtype=np.uint8)}
    msg = _fails(write_artefact, out, "test", data, config_digest="d")
    assert msg.startswith(f"{out}: cannot be written: no space left on device")
    assert list(tmp_path.iterdir()) == []  # no artefact, no hidden temporary


def test_full_disk_under_a_stage_exits_1_with_one_line(scene_h5, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(os, "pwrite", _pwrite_failing_after(100))
    out = tmp_path / "split.h5"
    with pytest.raises(SystemExit) as exc:
        stages.run_stage(stages.split, None, scene=str(scene_h5), out=str(out), ratio="0.6")
    assert exc.value.code == 1
    err = [line for line in capsys.readouterr().err.splitlines() if " INFO " not in line]
    assert len(err) == 1 and err[0].startswith(f"mogaf: error: {out}: cannot be written: no space left on device")
    assert list(tmp_path.iterdir()) == []


def test_full_file_system_is_refused_before_anything_is_opened(tmp_path, monkeypatch):
    full = os.statvfs(tmp_path)
    fields = dict(
        zip(
            (
                "f_bsize",
                "f_frsize",
                "f_blocks",
                "f_bfree",
                "f_bavail",
                "f_files",
                "f_ffree",
                "f_favail",
                "f_flag",
                "f_namemax",
            ),
            full,
        )
    )
    fields.update(f_bfree=0, f_bavail=0)
    monkeypatch.setattr(atomic.os, "statvfs", lambda path: os.statvfs_result(tuple(fields.values())))
    out = tmp_path / "a.h5"
    msg = _fails(write_artefact, out, "test", {"x": np.zeros(3)}, config_digest="d")
    assert msg == f"{out}: cannot be written: no space left on device (0 bytes free there); free some space and rerun"
    assert list(tmp_path.iterdir()) == []


def test_full_disk_writing_json_is_one_line(tmp_path, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.json, "dump", full)
    out = tmp_path / "metrics.json"
    assert "no space left on device" in _fails(write_json, out, {"a": 1})
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- outputs that are inputs
def test_split_out_equal_to_its_input_is_refused_and_the_input_kept(in_repo, scene_h5, tmp_path, capsys):
    x = tmp_path / "X.h5"
    shutil.copy(scene_h5, x)
    before = x.read_bytes()
    err = _cli_error(capsys, "split", "--scene-h5", str(x), "--out", str(x), "--ratio", "0.6")
    assert f"{x}: is also an input of this stage" in err and "refusing to overwrite" in err
    assert x.read_bytes() == before
    link = tmp_path / "link.h5"  # the same file under another name
    link.symlink_to(x)
    err = _cli_error(capsys, "split", "--scene-h5", str(x), "--out", str(link), "--ratio", "0.6")
    assert "is also an input of this stage" in err
    assert x.read_bytes() == before and link.is_symlink()


@pytest.mark.parametrize("target", ["scene.h5", "transforms_train.json", "train/new/scene.h5"])
def test_ingest_never_writes_inside_the_dataset_folder(in_repo, scene_copy, tmp_path, capsys, target):
    before = _snapshot(scene_copy)
    out = scene_copy / target
    err = _cli_error(
        capsys,
        "ingest",
        "--folder",
        str(scene_copy),
        "--out",
        str(out),
        "--layout",
        "dnerf",
        "--dataset",
        "fk",
        "--scene",
        "s",
        "--configfile",
        _dnerf_config(tmp_path, scene_copy),
    )
    assert f"{out}: lies inside the dataset folder {scene_copy.resolve()}" in err
    assert _snapshot(scene_copy) == before


def test_no_stage_writes_inside_a_dataset_folder(scene_h5, dataset):
    msg = _fails(stages.split, str(scene_h5), str(dataset / "test" / "split.h5"), "0.6")
    assert "lies inside the dataset folder" in msg and not (dataset / "test" / "split.h5").exists()


def test_other_outputs_that_would_overwrite_or_delete_inputs(tmp_path):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    a.write_text("input")
    folder = tmp_path / "renders"
    folder.mkdir()
    (folder / "in.h5").write_text("input")
    # a checkpoint on an input (it is removed after success), two outputs on one path,
    # a replaced folder holding an input
    assert "is also an input" in _fails(check_outputs, {"out": b, "checkpoint": a}, [a])
    assert "is given as both the out and the checkpoint output" in _fails(
        check_outputs, {"out": b, "checkpoint": b}, [a]
    )
    assert "holds the input" in _fails(check_outputs, {"renders": folder}, [folder / "in.h5"], directories=("renders",))
    check_outputs({"out": b, "checkpoint": tmp_path / "c.pt"}, [a])  # fine


def test_synthesize_does_not_replace_a_folder_of_other_files(in_repo, tmp_path, capsys):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    err = _cli_error(capsys, "synthesize", "--out", str(tmp_path / "mine"), "--scene", "default")
    assert "exists and is not a synthetic scene" in err
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


def test_out_an_existing_directory_is_one_line(in_repo, scene_h5, tmp_path, capsys):
    (tmp_path / "adir").mkdir()
    err = _cli_error(capsys, "split", "--scene-h5", str(scene_h5), "--out", str(tmp_path / "adir"), "--ratio", "0.6")
    assert f"{tmp_path / 'adir'}: is an existing directory" in err
    with pytest.raises(MogafError, match="is an existing directory"):  # the writer itself, for library callers
        write_json(tmp_path / "adir", {})


# ---------------------------------------------------------------- degenerate datasets
def _times(root: Path, split: str, times: list[float]) -> None:
    def edit(d):
        for fr, t in zip(d["frames"], times):
            fr["time"] = t

    _edit_json(root / f"transforms_{split}.json", edit)


def test_training_frames_all_at_one_time_are_refused(scene_copy):
    _times(scene_copy, "train", [0.0] * 6)
    msg = _fails(read_scene, "dnerf", scene_copy, dataset="fk", scene="s")
    assert msg.startswith(f"{scene_copy / 'transforms_train.json'}: its 6 training frame(s) are all at one time (0)")


def test_iphone_training_frames_at_one_time_are_refused(tmp_path):
    from support.fake_datasets import fake_iphone

    root = fake_iphone(tmp_path / "ip", num_times=3, val_cameras=1)
    _edit_json(root / "splits" / "train.json", lambda d: d.update(time_ids=[0, 0, 0]))
    _edit_json(
        root / "metadata.json", lambda d: [d[n].update(warp_id=0, appearance_id=0) for n in ("0_00001", "0_00002")]
    )
    msg = _fails(read_scene, "iphone", root, dataset="fk", scene="s")
    assert msg.startswith(f"{root / 'splits' / 'train.json'}: its 3 training frame(s) are all at one time (0)")


def test_observed_frames_at_one_time_step_are_refused_by_split(scene_copy, tmp_path):
    # training frames at 0 and 0.9 only: at ratio 0.6 one instant would stand for every observed step
    _times(scene_copy, "train", [0.0, 0.0, 0.0, 0.9, 0.9, 1.0])
    _times(scene_copy, "test", [0.1, 0.2, 0.3, 0.4])
    with pytest.warns(DatasetWarning, match="share time"):  # and no frame at steps 1..8 of the training span
        out = stages.ingest(str(scene_copy), str(tmp_path / "scene.h5"), "dnerf", {"num_timesteps": 11}, "fk", "s")
    msg = _fails(split_scene, out, 0.6)
    assert msg.startswith(f"{out}: the 3 training frame(s) before the cut at ratio 0.6 are all at time step 0")


def test_duplicate_frame_times_leaving_a_step_empty_warn(scene_copy):
    _times(scene_copy, "train", [0.0, 1 / 9, 1 / 9, 3 / 9, 4 / 9, 5 / 9])  # 2/9 lost: copied from frame 1
    _times(scene_copy, "test", [6 / 9, 7 / 9, 8 / 9, 1.0])
    with pytest.warns(DatasetWarning) as record:
        scene = read_scene("dnerf", scene_copy, dataset="fk", scene="s")
    found = [str(w.message) for w in record if w.category is DatasetWarning]
    assert len(found) == 1
    text = found[0]
    assert text.startswith(
        f"{scene_copy / 'transforms_train.json'}: frames 1 (./train/r_001) and 2 (./train/r_002) share time"
    )
    assert "time step(s) 2 of its frames' span have no frame" in text
    assert scene.num_timesteps == 10


def test_synchronised_views_sharing_times_do_not_warn(scene_copy):
    _times(scene_copy, "train", [0.0, 0.0, 0.5, 0.5, 1.0, 1.0])  # two cameras per instant, no step empty
    _times(scene_copy, "test", [0.0, 0.5, 1.0, 1.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", DatasetWarning)
        read_scene("dnerf", scene_copy, dataset="fk", scene="s")


def test_a_warning_under_a_stage_is_one_log_line(scene_copy, tmp_path, capsys):
    _times(scene_copy, "train", [0.0, 1 / 9, 1 / 9, 3 / 9, 4 / 9, 5 / 9])
    _times(scene_copy, "test", [6 / 9, 7 / 9, 8 / 9, 1.0])
    log = tmp_path / "logs" / "ingest.log"
    stages.run_stage(
        stages.ingest,
        log,
        folder=str(scene_copy),
        out=str(tmp_path / "scene.h5"),
        layout="dnerf",
        options={},
        dataset="fk",
        scene="s",
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mogaf: warning: ") and "share time" in err[0]
    assert "WARNING mogaf: " in log.read_text()


def test_empty_class_mapping_while_masks_carry_ids(scene_copy):
    (scene_copy / "class_mapping.json").write_text("{}")
    msg = _fails(read_scene, "dnerf", scene_copy, dataset="fk", scene="s")
    assert msg.startswith(f"{scene_copy / 'class_mapping.json'}: lists no class, but the mask")
    assert "has object id 1" in msg


@pytest.mark.parametrize(
    "text, words",
    [
        ('{"0": "background", "1": "ball", "2": "cloth", "1": "arm"}', "key '1' appears twice in one JSON object"),
        ('{"0": "background", "1": "ball", "2": "cloth", "01": "arm"}', "class id 1 is listed twice ('1' and '01')"),
    ],
)
def test_class_mapping_naming_one_id_twice(scene_copy, text, words):
    (scene_copy / "class_mapping.json").write_text(text)
    msg = _fails(read_scene, "dnerf", scene_copy, dataset="fk", scene="s")
    assert msg.startswith(f"{scene_copy / 'class_mapping.json'}: ") and words in msg


@pytest.mark.parametrize("split", ["train", "test"])
def test_transforms_with_no_frames_are_refused_and_no_scene_written(scene_copy, tmp_path, split):
    _edit_json(scene_copy / f"transforms_{split}.json", lambda d: d.update(frames=[]))
    out = tmp_path / "scene.h5"
    msg = _fails(stages.ingest, str(scene_copy), str(out), "dnerf", {}, "fk", "s")
    assert msg.startswith(f"{scene_copy / f'transforms_{split}.json'}: lists no frames")
    assert not out.exists() and list(tmp_path.glob(".scene.h5*")) == []


@pytest.mark.parametrize("file_path", ["../s2/train/r_000", "./train/../../s2/train/r_000", "/etc/passwd", "ABS"])
def test_file_path_leaving_the_scene_folder_is_refused(scene_copy, file_path):
    outside = scene_copy.parent / "s2" / "train"
    write_png(outside / "r_000.png", np.zeros((16, 16, 4), np.uint8))  # it exists: only where it lies is wrong
    path = str(outside / "r_000") if file_path == "ABS" else file_path
    _edit_json(scene_copy / "transforms_train.json", lambda d: d["frames"][0].update(file_path=path))
    msg = _fails(read_scene, "dnerf", scene_copy, dataset="fk", scene="s")
    assert msg.startswith(f"{scene_copy / 'transforms_train.json'}: frame 0") and "leaves the scene folder" in msg


@pytest.mark.parametrize("file_path", ["./", ".", "./train/.."])
def test_file_path_naming_the_scene_folder_is_refused(scene_copy, file_path):
    """Such a path would read the image beside the folder (`<scene>.png`)."""
    write_png(scene_copy.parent / f"{scene_copy.name}.png", np.zeros((16, 16, 4), np.uint8))
    _edit_json(scene_copy / "transforms_train.json", lambda d: d["frames"][0].update(file_path=file_path))
    msg = _fails(read_scene, "dnerf", scene_copy, dataset="fk", scene="s")
    assert msg.startswith(f"{scene_copy / 'transforms_train.json'}: frame 0") and "names the scene folder" in msg


# ---------------------------------------------------------------- tables
def _metrics(path: Path, **changes) -> Path:
    data = {
        "dataset": "d",
        "scene": "s",
        "ratio": 0.6,
        "variant": "default",
        "protocol": "dnerf",
        "methods": {
            "mogaf": {
                "image": {"psnr": 20.0, "ssim": 0.9, "lpips": 0.1},
                "tracking": None,
                "runtime": {"total_wall_s": 10.0},
            }
        },
    }
    data.update(changes)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    "change, words",
    [
        ({"ratio": 7}, "'ratio' must be a number in (0, 1), got 7"),
        (
            {"methods": {"mogaf": {"image": {"psnr": "abc"}}}},
            "'methods.mogaf.image.psnr' must be a number or null, got 'abc'",
        ),
        (
            {"methods": {"mogaf": {"image": {"psnr": True}}}},
            "'methods.mogaf.image.psnr' must be a number or null, got True",
        ),
        ({"scene": None}, "'scene' must be a non-empty string"),
        (
            {"methods": {"mogaf": {"image": {"psnr": 20.0, "ssim": 7.0}}}},
            "'methods.mogaf.image.ssim' is 7.0, outside the range [-1, 1] of ssim",
        ),
        (
            {"methods": {"mogaf": {"image": {"psnr": 20.0, "lpips": -3.0}}}},
            "'methods.mogaf.image.lpips' is -3.0, outside the range [0, inf] of lpips",
        ),
        (
            {"methods": {"mogaf": {"tracking": {"epe_3d": -0.5, "delta_3d@0.05": 0.4}}}},
            "'methods.mogaf.tracking.epe_3d' is -0.5, outside the range [0, inf] of epe_3d",
        ),
        (
            {"methods": {"mogaf": {"tracking": {"delta_3d@0.10": 1.5}}}},
            "'methods.mogaf.tracking.delta_3d@0.10' is 1.5, outside the range [0, 1] of delta_3d@0.10",
        ),
        ({"grouping": {"mean_iou": 2.0}}, "'grouping.mean_iou' is 2.0, outside the range [0, 1] of mean_iou"),
        (
            {"methods": {"mogaf": {"image": {"psnr": 10**400}}}},
            "'methods.mogaf.image.psnr' must be a number or null, got 1000",
        ),
        ({"methods": {"mogaf": {"forecast": "oops"}}}, "'methods.mogaf.forecast' must be an object"),
        ({"methods": {"mogaf": {"forecast": {"params": 3}}}}, "'methods.mogaf.forecast.params' must be an object"),
        ({"methods": {"mogaf": {"forecast": {"jobs": [1]}}}}, "'methods.mogaf.forecast.jobs' must be an object"),
        ({"grouping": {"per_object_iou": ["x"]}}, "'grouping.per_object_iou[0]' must be a number or null, got 'x'"),
        ({"grouping": {"per_part_iou": [None]}}, "'grouping.per_part_iou[0]' must be a number, got null"),
        ({"grouping": {"per_object_iou": 0.5}}, "'grouping.per_object_iou' must be a list"),
        ({"grouping": {"object_names": [1]}}, "'grouping.object_names' must be a list of names"),
    ],
)
def test_tables_refuse_a_bad_metrics_file(in_repo, tmp_path, capsys, change, words):
    bad = _metrics(tmp_path / "m.json", **change)
    err = _cli_error(capsys, "tables", str(bad), "--out-dir", str(tmp_path / "t"))
    assert f"{bad}: not a usable metrics.json: {words}" in err
    assert not (tmp_path / "t").exists()


def test_tables_refuse_json_nested_past_the_parsers_depth(in_repo, tmp_path, capsys):
    bad = tmp_path / "m.json"
    bad.write_text("[" * 100_000 + "]" * 100_000)
    err = _cli_error(capsys, "tables", str(bad), "--out-dir", str(tmp_path / "t"))
    assert err.startswith(f"mogaf: error: {bad}: not readable JSON (RecursionError")


def test_tables_refuse_a_ratio_that_contradicts_its_folder(in_repo, tmp_path, capsys):
    bad = _metrics(tmp_path / "results/d/s/ratio0.6/metrics.json", ratio=0.8)
    err = _cli_error(capsys, "tables", str(bad), "--out-dir", str(tmp_path / "t"))
    assert err == (
        f"mogaf: error: {bad}: says ratio 0.8, but lies in a folder of ratio 0.6; "
        "a metrics.json moved or edited by hand, rerun evaluate"
    )
    assert load_metrics([_metrics(tmp_path / "results/d/s/ratio0.8/metrics.json", ratio=0.8)])  # agreeing: read


def test_tables_refuse_nan(tmp_path):
    bad = _metrics(tmp_path / "m.json")
    bad.write_text(bad.read_text().replace("20.0", "NaN"))
    assert _fails(load_metrics, [bad]).startswith(f"{bad}: not readable JSON (ValueError: NaN is not a JSON number")


def test_tables_refuse_two_files_of_one_result(tmp_path):
    a = _metrics(tmp_path / "results/d/s/ratio0.6/metrics.json")
    b = _metrics(tmp_path / "results/d/s/ratio0.60/metrics.json")
    msg = _fails(load_metrics, [a, b])
    assert msg.startswith(f"{b}: holds the same result as {a} (d/s, ratio 0.6, variant default)")
    _metrics(b, variant="rt_fast")
    assert len(load_metrics([a, b])) == 2  # another variant of the scene is another result


# ---------------------------------------------------------------- config and names
def _snakemake(args: list[str], cwd: Path, timeout: int = 120) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), *args]
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def test_config_error_under_snakemake_names_the_file_and_the_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("recon: 5\n")  # Snakemake's own check printed the whole recon schema (about 100 lines)
    res = _snakemake(["-n", "-c1", "--configfile", str(CONFIG), str(bad)], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 1
    assert f"{bad}: recon: 5 is not of type 'object'" in out
    assert "Failed validating" not in out and len(out.splitlines()) < 10, out


def test_conflicting_forecaster_settings_are_refused_before_any_job(tmp_path):
    """A relation the schema cannot express (a select-only margin with the
    weighted blend) stops the workflow at load, in one line, not at the
    forecast after hours of reconstruction."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("forecast:\n  mogaf:\n    structured:\n      backtest_margin: 0.1\n")
    res = _snakemake(["-n", "-c1", "--configfile", str(CONFIG), str(bad)], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 1
    assert "forecast.mogaf.structured: backtest_margin applies to combine: select only (combine is weighted)" in out
    assert "Job stats" not in out
    # the same in an ablation variant, named
    ablations = tmp_path / "ablations.yaml"
    ablations.write_text(
        "variants:\n  margin:\n    description: x\n"
        "    overrides: {forecast: {mogaf: {structured: {backtest_margin: 0.1}}}}\n"
    )
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"ablations_file: {ablations}\n")
    res = _snakemake(["-n", "-c1", "--configfile", str(CONFIG), str(cfg)], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 1
    assert f"{ablations}: variant 'margin': forecast.mogaf.structured: backtest_margin applies" in out


def test_a_variant_cannot_change_the_scene_or_the_workflow(tmp_path, in_repo, capsys):
    """synthesize and ingest run once per scene, and the grid, demo and
    datasets once per workflow: a variant overriding them (here the rigidity
    table ingest applies) would be silently the default run. Refused by name,
    under Snakemake and on the command line."""
    ablations = tmp_path / "ablations.yaml"
    ablations.write_text(
        "variants:\n  relabel:\n    description: x\n    overrides: {rigidity: {'box*': nonrigid}, recon: {iterations: 5}}\n"
    )
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"ablations_file: {ablations}\n")
    line = f"{ablations}: ablation variant 'relabel' overrides rigidity: the scene and the workflow are the same"
    res = _snakemake(["-n", "-c1", "--configfile", str(CONFIG), str(cfg)], tmp_path)
    assert res.returncode == 1 and line in res.stdout + res.stderr
    merged = tmp_path / "merged.yaml"
    merged.write_text(yaml.safe_dump({**yaml.safe_load(CONFIG.read_text()), "ablations_file": str(ablations)}))
    args = ["split", "--scene-h5", "x.h5", "--out", str(tmp_path / "o.h5"), "--ratio", "0.6"]
    assert _cli_error(capsys, *args, "--configfile", str(merged), "--variant", "relabel").startswith(
        f"mogaf: error: {line}"
    )


def test_a_variant_a_scene_override_outranks_is_a_warning(tmp_path):
    """The dataset's overrides and scene_overrides are merged over a variant's:
    a variant setting a key they set does not change it for that scene, and
    the workflow says so when the variant is asked for."""
    shipped = yaml.safe_load((REPO / "config" / "ablations.yaml").read_text())
    shipped["variants"]["fewer"] = {"description": "x", "overrides": {"recon": {"iterations": 5}}}
    ablations = tmp_path / "ablations.yaml"
    ablations.write_text(yaml.safe_dump(shipped))
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(
        f"ablations_file: {ablations}\n"
        "datasets: {synthetic: {scene_overrides: {default: {recon: {iterations: 7}}}}}\n"
    )
    target = "results/synthetic/default/ratio0.6/ablation/fewer/metrics.json"
    res = _snakemake(["-n", "-c1", target, "--configfile", str(CONFIG), str(cfg)], tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    line = (
        f"{ablations}: variant 'fewer': recon.iterations does not change synthetic/default: "
        "the dataset's overrides or scene_overrides set it, and they win"
    )
    assert (res.stdout + res.stderr).count(line) == 1


def test_an_unknown_forecast_job_layout_is_one_line_naming_its_file(tmp_path):
    """forecast.jobs takes the layouts mogaf.forecast.params.JOB_LAYOUTS lists
    (the schema's enum is generated from them), refused before any job runs."""
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("forecast: {jobs: per_gaussian}\n")
    res = _snakemake(["-n", "-c1", "--configfile", str(CONFIG), str(cfg)], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 1
    assert f"{cfg}: forecast.jobs: 'per_gaussian' is not one of ['per_group', 'per_method']" in out
    assert not (tmp_path / "results").exists()


def test_a_forecaster_setting_without_effect_is_a_warning_naming_its_file(tmp_path):
    """Not an error (a sweep's variants switch the setting that makes it act):
    one warning line per value, naming the file that sets it, and the
    workflow goes on; a variant's own such value is said when the variant is
    asked for, naming the variant."""
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("forecast:\n  mogaf:\n    structured:\n      combine: select\n      backtest_neighbors: 8\n")
    res = _snakemake(["-n", "-c1", "--configfile", str(CONFIG), str(cfg)], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out
    line = "forecast.mogaf.structured.backtest_neighbors = 8 has no effect: combine is select, which decides per group"
    assert out.count(f"{cfg}: {line}") == 1
    assert "variant 'group_backtest'" not in out  # not asked for
    target = "results/synthetic/default/ratio0.6/ablation/group_backtest/metrics.json"
    res = _snakemake(["-n", "-c1", target, "--configfile", str(CONFIG), str(cfg)], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out
    ablations = REPO / "config" / "ablations.yaml"
    assert out.count(f"{ablations}: variant 'group_backtest': forecast.mogaf.structured.backtest_neighbors = 0") == 1
    # the shipped config has none
    res = _snakemake(["-n", "-c1", "--configfile", str(CONFIG)], tmp_path)
    assert "has no effect" not in res.stdout + res.stderr


@pytest.mark.parametrize(
    "where, edit",
    [
        ("datasets.dnerf.scenes.0", lambda c: c["datasets"]["dnerf"].update(scenes=["lego/x"])),
        ("demo.scene", lambda c: c["demo"].update(scene="my scene")),
        ("grid.0.scenes.0", lambda c: c.update(grid=[{"dataset": "dnerf", "scenes": [".."], "ratios": [0.6]}])),
        ("datasets", lambda c: c["datasets"].update({"my data": c["datasets"]["dnerf"]})),
        ("synthetic", lambda c: c["synthetic"].update({"a/b": {}})),
    ],
)
def test_scene_and_dataset_names_with_slash_or_space_are_refused(where, edit):
    cfg = yaml.safe_load(CONFIG.read_text())
    assert config_error(cfg, SCHEMA, [("config.yaml", cfg)]) is None
    edit(cfg)
    msg = str(config_error(cfg, SCHEMA, [("config.yaml", cfg)]))
    assert msg.startswith(f"config.yaml: {where}: ") and "no slash or space" in msg and "\n" not in msg


def test_the_cli_names_a_bad_scene_name_in_one_line(in_repo, tmp_path, capsys):
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["datasets"]["iphone"]["scenes"].append("a b")
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    err = _cli_error(
        capsys,
        "priors",
        "--scene-h5",
        "s.h5",
        "--split-h5",
        "p.h5",
        "--out",
        str(tmp_path / "o.h5"),
        "--configfile",
        str(tmp_path / "cfg.yaml"),
    )
    assert "cfg.yaml: datasets.iphone.scenes.5: 'a b' does not match" in err


# ---------------------------------------------------------------- read-only results folder
def _read_only(folder: Path) -> bool:
    """Make `folder` read-only for this process: a read-only bind mount as
    root (permissions do not bind root), else its permission bits."""
    if os.geteuid() == 0:
        res = subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True)
        if res.returncode != 0:
            return False
        res = subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], capture_output=True)
        if res.returncode != 0:
            subprocess.run(["umount", str(folder)], check=False)
            return False
        return True
    for path in [folder, *folder.rglob("*")]:
        path.chmod(0o555)
    return not os.access(folder, os.W_OK)


def _writable_again(folder: Path) -> None:
    if os.geteuid() == 0:
        subprocess.run(["umount", str(folder)], check=False)
    for path in [folder, *folder.rglob("*")]:
        path.chmod(0o755)


def test_read_only_results_folder_under_snakemake_is_one_line(dataset, tmp_path):
    work = tmp_path / "work"
    (work / "results" / "fk" / "s" / "logs").mkdir(parents=True)
    configfile = _dnerf_config(tmp_path, dataset)
    results = work / "results"
    if not _read_only(results):
        pytest.skip("cannot make a folder read-only here (root without mount rights)")
    try:
        res = _snakemake(["-c1", "results/fk/s/scene.h5", "--configfile", configfile], work)
    finally:
        _writable_again(results)
    out = res.stdout + res.stderr
    assert res.returncode == 1
    assert f"{results / 'fk' / 's'}: not writable (" in out and "rule ingest writes results/fk/s/scene.h5 there" in out
    assert "Traceback" not in out, out[-3000:]


def test_unwritable_folder_names_the_nearest_existing_folder(tmp_path, monkeypatch):
    assert unwritable_folder(tmp_path / "a" / "b" / "c.h5") is None
    monkeypatch.setattr(os, "access", lambda path, mode: Path(path) != tmp_path)
    folder, reason = unwritable_folder(tmp_path / "a" / "b" / "c.h5")
    assert folder == tmp_path and reason in ("no write permission", "a read-only file system")
    (tmp_path / "afile").write_text("")
    assert unwritable_folder(tmp_path / "afile" / "c.h5") == (tmp_path / "afile", "a file, not a folder")


def test_log_file_that_cannot_be_created_is_one_line(scene_h5, tmp_path, capsys):
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as exc:
        stages.run_stage(
            stages.split,
            tmp_path / "file" / "split.log",
            scene=str(scene_h5),
            out=str(tmp_path / "split.h5"),
            ratio="0.6",
        )
    assert exc.value.code == 1
    err = _one_line(capsys.readouterr().err.strip())
    assert f"{tmp_path / 'file' / 'split.log'}: cannot be written" in err


# ---------------------------------------------------------------- one line instead of a traceback
def test_negative_threads_are_one_line(in_repo, scene_h5, tmp_path, capsys):
    err = _cli_error(
        capsys,
        "split",
        "--scene-h5",
        str(scene_h5),
        "--out",
        str(tmp_path / "s.h5"),
        "--ratio",
        "0.6",
        "--threads",
        "-3",
    )
    assert err == "mogaf: error: threads must be a positive integer, got -3"


def _edited_scene(scene_h5: Path, out: Path, edit) -> Path:
    shutil.copy(scene_h5, out)
    with h5py.File(out, "r+") as fh:
        edit(fh)
    return out


def _w2c_3x4(fh) -> None:
    w2c = fh["frames/w2c"][()]
    del fh["frames/w2c"]
    fh.create_dataset("frames/w2c", data=w2c[:, :3, :], fletcher32=True)


@pytest.mark.parametrize(
    "edit, words",
    [
        (_w2c_3x4, "entry 'frames/w2c' has shape (10, 3, 4), expected (10, 4, 4)"),
        (
            lambda fh: fh.attrs.__setitem__("num_timesteps", -5),
            "attribute num_timesteps is -5; it must be an integer in [1, 16777216]",
        ),
        (lambda fh: fh.attrs.__setitem__("mogaf_format_version", "1"), "format version '1' is a str, not an integer"),
    ],
)
def test_malformed_scene_h5_is_one_line(in_repo, scene_h5, tmp_path, capsys, edit, words):
    bad = _edited_scene(scene_h5, tmp_path / "bad.h5", edit)
    err = _cli_error(capsys, "split", "--scene-h5", str(bad), "--out", str(tmp_path / "s.h5"), "--ratio", "0.6")
    assert f"{bad}: {words}" in err


def test_a_later_stage_refuses_a_w2c_of_the_wrong_shape(scene_h5, tmp_path):
    from mogaf.split import load_frames

    split_h5 = stages.split(str(scene_h5), str(tmp_path / "split.h5"), "0.6")
    bad = _edited_scene(scene_h5, tmp_path / "bad.h5", _w2c_3x4)
    assert "entry 'frames/w2c' has shape (10, 3, 4)" in _fails(load_frames, bad, split_h5, "observed")


def _tiny_model(path: Path, n: int) -> Path:
    rng = np.random.default_rng(0)
    fg = GaussianSet(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
        log_scales=np.full((n, 3), -3.0, np.float32),
        opacity_logits=np.zeros(n, np.float32),
        color_logits=np.zeros((n, 3), np.float32),
    )
    steps = np.arange(4)
    model = Model4D(
        fg=fg,
        motion_coef_logits=np.zeros((n, 1), np.float32),
        rot6d=np.tile(np.array([1.0, 0, 0, 0, 1, 0], np.float32), (1, 4, 1)),
        translations=np.zeros((1, 4, 3), np.float32),
        timesteps=steps,
        trajectory_means=np.repeat(fg.means[:, None], 4, axis=1),
        trajectory_quats=np.repeat(fg.quats[:, None], 4, axis=1),
    )
    return save_model(path, "recon", model, config_digest="t")


@pytest.mark.parametrize("stage", ["rigid_init", "forecast_group"])
def test_groups_shorter_than_the_model_are_one_line(tmp_path, stage):
    model = _tiny_model(tmp_path / "recon.h5", 12)
    groups = write_groups(
        tmp_path / "groups.h5",
        Groups(
            group_id=np.repeat([0, 1], 5),
            rigid=np.array([1, 1], np.int8),
            static=np.array([0, 0], np.int8),
            instance_id=-np.ones(2, np.int64),
            names=["a", "b"],
            rigid_source=["config"] * 2,
            method="ours",
            params={},
        ),
    )
    out = str(tmp_path / "out.h5")
    if stage == "rigid_init":
        msg = _fails(stages.rigid_init, str(model), str(groups), out, {})
    else:
        msg = _fails(
            stages.forecast_group,
            str(model),
            str(groups),
            str(tmp_path / "split.h5"),
            out,
            {},
            method="constant_velocity",
            group="all",
            seed=0,
        )
    assert msg.startswith(f"{groups}: assigns groups to 10 Gaussians, but the model {model} has 12")


# ---------------------------------------------------------------- artefacts changed on disk
def _overwrite_in_file(path: Path, dataset: str, raw: bytes, chunk: int = 0) -> None:
    """Overwrite bytes of a dataset's stored chunk in place, behind HDF5's back."""
    with h5py.File(path, "r") as fh:
        info = fh[dataset].id.get_chunk_info(chunk)
        offset, size = info.byte_offset, info.size
    assert len(raw) <= size
    with open(path, "r+b") as fh:
        fh.seek(offset)
        fh.write(raw)


def test_an_artefact_changed_on_disk_is_refused_naming_the_entry(tmp_path):
    from mogaf.representation import load_model

    model = _tiny_model(tmp_path / "recon.h5", 12)
    load_model(model)  # intact: reads
    _overwrite_in_file(model, "trajectories/means", np.array([0.25, 0.5, 0.75], np.float32).tobytes())  # finite
    msg = _fails(load_model, model)
    assert msg == (
        f"{model}: entry 'trajectories/means' fails its checksum: the file changed on disk after it was written; "
        "rerun the stage that wrote it"
    )
    # a stage reading the damaged model stops the same way, with nothing written
    groups = write_groups(
        tmp_path / "groups.h5",
        Groups(
            group_id=np.zeros(12, np.int64),
            rigid=np.array([1], np.int8),
            static=np.array([0], np.int8),
            instance_id=-np.ones(1, np.int64),
            names=["a"],
            rigid_source=["config"],
            method="ours",
            params={},
        ),
    )
    assert "fails its checksum" in _fails(stages.rigid_init, str(model), str(groups), str(tmp_path / "o.h5"), {})
    assert not (tmp_path / "o.h5").exists()


def test_a_partial_read_of_a_changed_artefact_is_refused(scene_h5, tmp_path):
    from mogaf.artefact import open_artefact, read_rows

    bad = tmp_path / "scene.h5"
    shutil.copy(scene_h5, bad)
    _overwrite_in_file(bad, "frames/K", np.eye(3, dtype=np.float64).tobytes()[:24])
    with open_artefact(bad) as fh, pytest.raises(MogafError) as err:
        read_rows(fh, "frames/K", np.array([0]))
    assert str(err.value).startswith(f"{bad}: entry 'frames/K' fails its checksum")


def test_a_changed_string_or_scalar_entry_is_refused(tmp_path):
    from mogaf.artefact import read_artefact

    path = write_artefact(
        tmp_path / "a.h5", "demo", {"names": ["left", "right"], "count": np.int64(3)}, config_digest="d"
    )
    assert read_artefact(path, "demo")["names"] == ["left", "right"]
    for key, value in (("names", np.array(["left", "wrong"], dtype=h5py.string_dtype())), ("count", np.int64(4))):
        edited = tmp_path / f"{key}.h5"
        shutil.copy(path, edited)
        with h5py.File(edited, "r+") as fh:
            fh[key][()] = value  # the stored checksum stays the old one
        assert _fails(read_artefact, edited, "demo").startswith(f"{edited}: entry '{key}' fails its checksum")


def test_an_entry_without_a_checksum_is_refused(tmp_path):
    from mogaf.artefact import read_artefact

    path = write_artefact(tmp_path / "a.h5", "demo", {"x": np.zeros((4, 3))}, config_digest="d")
    with h5py.File(path, "r+") as fh:
        del fh["x"]
        fh["x"] = np.ones((4, 3))  # a dataset written by hand: no checksum
    assert _fails(read_artefact, path, "demo") == (
        f"{path}: entry 'x' has no checksum: not written by this mogaf; rerun the stage"
    )


# ---------------------------------------------------------------- ingest: what used to pass silently
def test_one_rgb_frame_in_an_rgba_scene_is_refused_naming_it(scene_copy):
    frame = scene_copy / "train" / "r_002.png"
    write_png(frame, np.zeros((16, 16, 3), np.uint8))  # its background cannot be composited like the others'
    msg = _fails(read_scene, "dnerf", scene_copy, dataset="fk", scene="s")
    assert msg.startswith(f"{frame}: image has no alpha channel, but other frames of the scene do (e.g. ./train/r_000)")


def test_a_camera_far_outside_the_scene_is_refused_at_ingest(scene_copy):
    def far(d):
        d["frames"][3]["transform_matrix"][0][3] = 1e300

    _edit_json(scene_copy / "transforms_train.json", far)
    msg = _fails(read_scene, "dnerf", scene_copy, dataset="fk", scene="s")
    assert msg == (
        f"{scene_copy / 'transforms_train.json'}: frame 3 (./train/r_003): "
        "camera centre has a coordinate of 1e+300 (at most 1e+08)"
    )

    def outlier(d):
        d["frames"][3]["transform_matrix"][0][3] = 1e5  # finite and representable, but 10^4 scene extents away

    _edit_json(scene_copy / "transforms_train.json", outlier)
    msg = _fails(read_scene, "dnerf", scene_copy, dataset="fk", scene="s")
    assert msg.startswith(f"{scene_copy / 'transforms_train.json'}: frame 3 (./train/r_003): camera centre lies 1e+05")
    assert "times the scene's extent" in msg


def test_masks_that_are_all_background_warn_at_ingest_naming_the_folder(scene_copy):
    for mask in sorted(scene_copy.glob("*/masks/*.png")):
        write_png(mask, np.zeros((16, 16), np.uint8))
    with pytest.warns(DatasetWarning) as record:
        read_scene("dnerf", scene_copy, dataset="fk", scene="s")
    messages = [str(w.message) for w in record]
    assert any(
        m.startswith(f"{scene_copy / 'train' / 'masks'}: every object-id mask is all background") for m in messages
    )


def test_reconstruction_without_any_foreground_warns_at_ingest_and_names_the_scene(tmp_path):
    """An iPhone scene whose foreground masks are all empty: ingest warns
    naming the mask folder; recon's error names the scene and says why."""
    from support.fake_datasets import fake_iphone

    data = fake_iphone(tmp_path / "data" / "s", num_times=8, track_points=20)
    mask_dir = data / "flow3d_preprocessed" / "track_anything" / "2x"
    for mask in sorted(mask_dir.glob("*.png")):
        write_png(mask, np.zeros((12, 16), np.uint8))
    scene = tmp_path / "scene.h5"
    with pytest.warns(DatasetWarning, match=f"{mask_dir}: every foreground mask is empty"):
        stages.ingest(str(data), str(scene), "iphone", {}, "fk", "s")
    stages.split(str(scene), str(tmp_path / "split.h5"), "0.6")
    stages.priors(str(scene), str(tmp_path / "split.h5"), str(tmp_path / "priors.h5"), {}, 0)
    params = {"iterations": 5, "num_fg_init": 100, "num_bg_init": 100}
    msg = _fails(
        stages.recon,
        str(scene),
        str(tmp_path / "split.h5"),
        str(tmp_path / "priors.h5"),
        str(tmp_path / "r.h5"),
        params,
        0,
    )
    assert msg == (
        f"{scene}: reconstruction init: fewer than 8 foreground tracks could be lifted with depth; "
        "every foreground mask of its observed frames is empty"
    )
    assert not (tmp_path / "r.h5").exists()


# ---------------------------------------------------------------- images smaller than a metric's window
def test_a_scene_smaller_than_the_ssim_window_reconstructs(scene_h5, tmp_path):
    """16x16 images: the coarse level (8x8) is below the 11 px SSIM window,
    which used to end recon in a 41-line convolution traceback."""
    from mogaf.representation import load_model

    split = stages.split(str(scene_h5), str(tmp_path / "split.h5"), "0.6")
    priors = stages.priors(str(scene_h5), str(split), str(tmp_path / "priors.h5"), {}, 0)
    params = {"iterations": 10, "num_fg_init": 100, "num_bg_init": 100, "coarse_downscale": 2}
    out = stages.recon(str(scene_h5), str(split), str(priors), str(tmp_path / "recon.h5"), params, 0, device="cpu")
    assert load_model(out).fg.means.shape[0] > 0


def test_the_training_ssim_fits_its_window_to_small_images():
    import torch

    from mogaf.recon.losses import ssim

    torch.manual_seed(0)
    for side in (8, 9, 10, 1):
        a, b = torch.rand(1, side, side, 3), torch.rand(1, side, side, 3)
        assert torch.isfinite(ssim(a, b)) and ssim(a, a).item() == pytest.approx(1.0, abs=1e-5)
    a = torch.rand(1, 11, 13, 3)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize(
    "side, left_out",
    [(32, set()), (16, {"lpips"}), (8, {"lpips", "ssim"})],
)
def test_metrics_a_small_image_cannot_have_are_left_out_and_said(side, left_out):
    from mogaf.metrics import image_metrics, metrics_left_out

    rng = np.random.default_rng(0)
    pred, gt = rng.uniform(size=(side, side, 3)), rng.uniform(size=(side, side, 3))
    reasons = metrics_left_out(side, side, use_lpips=True)
    assert set(reasons) == left_out
    assert all(f"images are {side}x{side}" in why for why in reasons.values())
    measured = image_metrics(pred, gt, None, masked=True, use_lpips=True)
    expected = {"psnr", "ssim", "lpips", "mpsnr", "mssim", "mlpips"}
    for metric in left_out:
        expected -= {metric, f"m{metric}"}
    assert set(measured) == expected and all(np.isfinite(list(measured.values())))


def test_results_linked_into_a_dataset_is_refused_before_anything_is_created(scene_copy, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (work / "results").symlink_to(scene_copy, target_is_directory=True)
    before = sorted(scene_copy.rglob("*"))  # folders too: logs/ and benchmarks/ were created here
    res = _snakemake(["-c1", "results/fk/s/scene.h5", "--configfile", _dnerf_config(tmp_path, scene_copy)], work)
    out = res.stdout + res.stderr
    assert res.returncode == 1
    assert (
        f"results: lies inside the dataset folder {scene_copy.resolve()} (it links to {scene_copy.resolve()}); "
        "no stage writes into a dataset" in out
    ), out[-3000:]
    assert sorted(scene_copy.rglob("*")) == before


def test_an_unknown_top_level_key_names_the_one_file_that_holds_it(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("recno:\n  iterations: 3\n")
    res = _snakemake(["-n", "-c1", "--configfile", "config/config.yaml", str(bad)], REPO)
    out = res.stdout + res.stderr
    assert res.returncode == 1
    assert f"\n{bad}: recno: Additional properties are not allowed ('recno' was unexpected)" in out, out
    assert "config/config.yaml +" not in out  # neither the other layers nor config.yaml twice


def test_cli_names_checks_its_scene_flag_and_its_config(in_repo, tmp_path, capsys):
    args = ["split", "--scene-h5", "x.h5", "--out", str(tmp_path / "o.h5"), "--ratio", "0.6"]
    err = _cli_error(capsys, *args, "--dataset", "synthetic", "--scene", "my scene/../x")
    assert err == (
        "mogaf: error: --scene 'my scene/../x' is not a valid name: a dataset or scene name: letters, digits, "
        "'_', '-' and '.', not starting with '.'; no slash or space"
    )
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    err = _cli_error(capsys, *args, "--configfile", str(empty))
    assert err == f"mogaf: error: {empty}: is empty; give the pipeline config (config/config.yaml) or a copy of it"
    cfg = _dnerf_config(tmp_path, tmp_path / "s")
    err = _cli_error(capsys, *args, "--configfile", cfg, "--dataset", "nosuch", "--scene", "s")
    assert err.startswith(f"mogaf: error: {cfg}: unknown dataset 'nosuch' (the config's datasets: ")


# ---------------------------------------------------------------- full disk outside the HDF5 writer
def _only_filler(folder: Path) -> None:
    assert sorted(p.name for p in folder.iterdir()) == ["filler"]  # nothing written, no hidden temporary


def test_full_disk_writing_a_checkpoint_is_one_line(nearly_full_disk):
    import torch

    from mogaf.recon.checkpoint import save_checkpoint

    out = nearly_full_disk / "recon.ckpt"
    msg = _fails(save_checkpoint, out, {"weights": torch.arange(100_000, dtype=torch.float32)})  # 400 KB
    assert msg.startswith(f"{out}: cannot be written: no space left on device")
    _only_filler(nearly_full_disk)


def test_full_disk_writing_renders_and_videos_is_one_line(nearly_full_disk):
    from mogaf.artefact import atomic_folder
    from mogaf.evaluate.images import _save_png, _write_video, video_encoder

    def in_background(tmp):
        with video_encoder() as write_video:  # as the evaluation writes its videos
            write_video(tmp / "m.mp4", frames, 10)

    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (96, 128, 3), dtype=np.uint8) for _ in range(12)]  # noise: ~400 KB encoded
    out = nearly_full_disk / "renders"
    for write in (
        lambda tmp: [_save_png(tmp / f"{i}.png", f / 255.0) for i, f in enumerate(frames)],
        lambda tmp: _write_video(tmp / "m.mp4", frames, 10),
        in_background,
    ):
        with pytest.raises(MogafError) as err:
            with atomic_folder(out) as tmp:
                write(tmp)
        assert str(err.value).startswith(f"{out}: cannot be written: no space left on device"), err.value
        _only_filler(nearly_full_disk)


def test_full_disk_synthesizing_a_scene_is_one_line(nearly_full_disk):
    from mogaf.synth.generate import generate_scene

    out = nearly_full_disk / "scene"
    msg = _fails(generate_scene, out, {"preset": "default", "width": 64, "height": 48, "num_frames": 12})
    assert msg.startswith(f"{out}: cannot be written: no space left on device")
    _only_filler(nearly_full_disk)


def test_a_bad_core_count_fails_every_stage_at_its_start(monkeypatch, capsys):
    """MOGAF_CORES is checked before the stage runs, also in a stage that
    never asks how many cores it may use."""
    monkeypatch.setenv("MOGAF_CORES", "two")
    with pytest.raises(SystemExit) as exc:
        stages.run_stage(lambda: pytest.fail("the stage ran with a bad MOGAF_CORES"))
    assert exc.value.code == 1
    assert "MOGAF_CORES must be a whole number >= 1, got 'two'" in _one_line(capsys.readouterr().err.strip())
    monkeypatch.setenv("MOGAF_CORES", " ")  # blank: unset
    assert stages.run_stage(lambda: 7) == 7


# ---------------------------------------------------------------- malformed config, artefact headers, paths
def test_cli_config_files_that_cannot_be_read_or_have_wrong_types(in_repo, tmp_path, capsys):
    args = ["split", "--scene-h5", "x.h5", "--out", str(tmp_path / "o.h5"), "--ratio", "0.6"]
    assert (
        _cli_error(capsys, *args, "--configfile", str(tmp_path))
        == f"mogaf: error: {tmp_path}: is a folder, not a YAML file"
    )
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(b"seed: 0 # \xff\n")
    assert _cli_error(capsys, *args, "--configfile", str(latin)).startswith(f"mogaf: error: {latin}: not UTF-8 text")
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["datasets"]["synthetic"] = 5  # read by the scene's overrides before the merged config is checked
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(cfg))
    err = _cli_error(capsys, *args, "--configfile", str(bad), "--dataset", "synthetic", "--scene", "default")
    assert err == f"mogaf: error: {bad}: datasets.synthetic: 5 is not of type 'object'"
    ablations = tmp_path / "ablations.yaml"
    ablations.write_text("variants:\n")
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["ablations_file"] = str(ablations)
    bad.write_text(yaml.safe_dump(cfg))
    err = _cli_error(capsys, *args, "--configfile", str(bad), "--variant", "v")
    assert err == f"mogaf: error: {ablations}: variants: None is not of type 'object'"


@pytest.mark.parametrize(
    "attr, value, message",
    [
        ("mogaf_stage", None, "names no stage that wrote it"),
        ("num_timesteps", "json:{", "attribute num_timesteps is not valid JSON"),
        (
            "mogaf_input_digests",
            'json:{"split": 5}',
            "attributes mogaf_input_digests / mogaf_lineage_digest are malformed",
        ),
        ("layout", np.array([1, 2]), "attribute layout is array([1, 2])"),
        ("num_timesteps", 2**40, "attribute num_timesteps is 1099511627776; it must be an integer in [1, 16777216]"),
    ],
)
def test_artefact_attributes_another_tool_wrote_are_refused(scene_h5, tmp_path, attr, value, message):
    scene = Path(shutil.copy(scene_h5, tmp_path / "scene.h5"))
    with h5py.File(scene, "r+") as fh:
        if value is None:
            del fh.attrs[attr]
        else:
            fh.attrs[attr] = value
    out = tmp_path / "split.h5"
    assert _fails(stages.split, scene=str(scene), out=str(out), ratio="0.6").startswith(f"{scene}: {message}")
    assert not out.exists()


def test_a_name_longer_than_the_file_system_allows_is_one_line(scene_h5, tmp_path):
    long = tmp_path / ("x" * 300 + ".h5")
    msg = _fails(stages.split, scene=str(scene_h5), out=str(long), ratio="0.6")
    assert msg == f"{long}: has a file or folder name longer than 255 bytes; give a shorter path"
    msg = _fails(stages.split, scene=str(long), out=str(tmp_path / "split.h5"), ratio="0.6")
    assert msg.startswith(f"{long}: cannot be opened (")
    assert list(tmp_path.iterdir()) == []


def test_scene_frame_times_that_are_not_numbers_are_refused(scene_h5, tmp_path):
    scene = Path(shutil.copy(scene_h5, tmp_path / "scene.h5"))
    with h5py.File(scene, "r+") as fh:
        n = fh["frames/time_index"].shape[0]
        del fh["frames/time_index"]
        strings = np.array(["0"] * n, dtype=h5py.string_dtype())
        fh["frames/time_index"] = strings
        fh["frames/time_index"].attrs[ATTR_CHECKSUM] = dataset_checksum(strings)  # as another tool might
    out = tmp_path / "split.h5"
    msg = _fails(stages.split, scene=str(scene), out=str(out), ratio="0.6")
    assert msg.startswith(f"{scene}: entry 'frames/time_index' holds object, not numbers")
    assert not out.exists()
