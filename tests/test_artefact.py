"""The HDF5 artefact layer: atomic writes, attrs, refusal of bad files."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest

from mogaf import __version__
from mogaf.artefact import (
    ATTR_FORMAT,
    ATTR_PACKAGE,
    FORMAT_VERSION,
    config_digest,
    open_artefact,
    read_artefact,
    read_rows,
    write_artefact,
    write_json,
)
from mogaf.errors import MogafError


def _write(path, **kw):
    data = {"a": np.arange(6, dtype=np.float32).reshape(3, 2), "g": {"b": np.ones(4, np.int64), "names": ["x", "y"]}}
    return write_artefact(path, "demo", data, config_digest="abc", attrs={"note": "hi", "nested": {"k": 0.5}}, **kw)


def test_roundtrip_attrs_and_nested(tmp_path):
    path = _write(tmp_path / "x.h5")
    art = read_artefact(path, "demo")
    assert art.stage == "demo" and art.config_digest == "abc" and art.package_version == __version__
    assert art.created_utc.endswith("+00:00")
    np.testing.assert_array_equal(art["a"], np.arange(6, dtype=np.float32).reshape(3, 2))
    assert art["g/names"] == ["x", "y"]
    assert art.attrs == {"note": "hi", "nested": {"k": 0.5}}
    assert "g/b" in art and "g/zz" not in art


def test_missing_entry_or_attribute_is_an_input_error_naming_the_file(tmp_path):
    path = _write(tmp_path / "x.h5")
    art = read_artefact(path, "demo")
    with pytest.raises(MogafError, match=r"x\.h5: has no attribute 'ratio' \(stage demo\)"):
        art.attrs["ratio"]
    assert art.attrs.get("ratio") is None and art.attrs["note"] == "hi"
    with pytest.raises(MogafError, match=r"x\.h5: lacks an entry or attribute its reader needs .*zz"):
        with open_artefact(path, "demo") as fh:
            fh["g/zz"]
    with pytest.raises(MogafError, match=r"x\.h5: lacks an entry or attribute its reader needs .*ratio"):
        with open_artefact(path, "demo") as fh:
            fh.attrs["ratio"]


def test_refuses_non_finite_and_leaves_nothing(tmp_path):
    path = tmp_path / "bad.h5"
    with pytest.raises(MogafError, match="non-finite values in 'g/x'"):
        write_artefact(path, "demo", {"g": {"x": np.array([1.0, np.nan])}}, config_digest="d")
    assert not path.exists()
    assert not list(tmp_path.iterdir()), "no temporary file may survive a failed write"


def test_refuses_non_finite_attr(tmp_path):
    with pytest.raises(MogafError):
        write_artefact(tmp_path / "a.h5", "demo", {}, config_digest="d", attrs={"x": float("inf")})
    with pytest.raises(MogafError):
        write_artefact(tmp_path / "b.h5", "demo", {}, config_digest="d", attrs={"x": {"y": float("nan")}})


def test_stage_version_digest_checks(tmp_path):
    path = _write(tmp_path / "x.h5")
    with pytest.raises(MogafError, match="written by stage 'demo', expected 'recon'"):
        read_artefact(path, "recon")
    with pytest.raises(MogafError, match="config digest abc does not match"):
        read_artefact(path, "demo", expected_config_digest="zzz")
    with h5py.File(path, "r+") as fh:
        fh.attrs[ATTR_FORMAT] = FORMAT_VERSION + 1
    with pytest.raises(MogafError, match=f"format version {FORMAT_VERSION + 1}"):
        read_artefact(path, "demo")


def test_incompatible_package_version(tmp_path):
    path = _write(tmp_path / "x.h5")
    with h5py.File(path, "r+") as fh:
        fh.attrs[ATTR_PACKAGE] = "99.0.0"
    with pytest.raises(MogafError, match="incompatible"):
        read_artefact(path, "demo")


def test_truncated_and_foreign_files(tmp_path):
    path = _write(tmp_path / "x.h5")
    data = path.read_bytes()
    trunc = tmp_path / "trunc.h5"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(MogafError) as err:
        read_artefact(trunc, "demo")
    assert str(trunc) in str(err.value) and "\n" not in str(err.value)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as fh:
        fh["x"] = np.zeros(3)
    with pytest.raises(MogafError, match="not a MoGaF artefact"):
        read_artefact(foreign, "demo")
    with pytest.raises(MogafError, match="missing"):
        read_artefact(tmp_path / "nope.h5", "demo")


def test_nan_inside_is_refused_on_read(tmp_path):
    path = _write(tmp_path / "x.h5")
    with h5py.File(path, "r+") as fh:
        fh["a"][0, 0] = np.nan
    with pytest.raises(MogafError, match="entry 'a' contains non-finite values"):
        read_artefact(path, "demo")


def test_inputs_are_opened_read_only(tmp_path):
    path = _write(tmp_path / "x.h5")
    os.chmod(path, 0o444)
    try:
        with open_artefact(path, "demo") as fh:
            assert fh.mode == "r"
            rows = read_rows(fh, "a", np.array([2, 0, 2]))
        np.testing.assert_array_equal(rows, np.array([[4, 5], [0, 1], [4, 5]], np.float32))
    finally:
        os.chmod(path, 0o644)


def test_read_rows_checks_bounds(tmp_path):
    path = _write(tmp_path / "x.h5")
    with open_artefact(path, "demo") as fh:
        with pytest.raises(MogafError, match="has 3 rows"):
            read_rows(fh, "a", np.array([3]))


@pytest.mark.parametrize("chunks", [None, (4, 3), (1, 3)])
def test_read_rows_equals_h5py_selection_for_any_rows(tmp_path, chunks):
    """read_rows reads slices (spans with gaps up to a chunk's rows) instead of
    h5py's slow list selection: the same rows in the asked order, duplicates
    included, from contiguous and chunked (compressed) datasets; the slow
    reference is h5py's own selection."""
    from mogaf.artefact.reader import row_spans

    assert row_spans(np.array([0, 1, 2, 5, 6, 30]), 1) == [(0, 3), (5, 7), (30, 31)]
    assert row_spans(np.array([0, 1, 2, 5, 6, 30]), 2) == [(0, 7), (30, 31)]
    data = np.arange(40 * 3, dtype=np.float32).reshape(40, 3)
    path = tmp_path / "rows.h5"
    with h5py.File(path, "w") as fh:
        fh.create_dataset("a", data=data, chunks=chunks, compression="gzip" if chunks else None)
    rng = np.random.default_rng(0)
    with h5py.File(path, "r") as fh:
        for _ in range(50):
            rows = rng.integers(0, 40, size=rng.integers(1, 30))
            got = read_rows(fh, "a", rows)
            np.testing.assert_array_equal(got, fh["a"][np.unique(rows)][np.searchsorted(np.unique(rows), rows)])
            np.testing.assert_array_equal(got, data[rows])
        assert read_rows(fh, "a", np.zeros(0, np.int64)).shape == (0, 3)


def test_killed_writer_leaves_no_artefact(tmp_path):
    """SIGKILL in the middle of a write: the final name never appears."""
    out = tmp_path / "big.h5"
    code = textwrap.dedent(
        f"""
        import os, signal, numpy as np
        import mogaf.artefact.writer as A
        real = A._write_tree
        def slow(group, data, path, prefix="", content=None):
            real(group, data, path, prefix, content)
            os.kill(os.getpid(), signal.SIGKILL)
        A._write_tree = slow
        A.write_artefact({str(out)!r}, "demo", {{"a": np.zeros(10)}}, config_digest="d")
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()
    leftovers = list(tmp_path.iterdir())
    assert leftovers and all(p.name.startswith(".big.h5.tmp-") for p in leftovers)
    # The next write cleans the stale temporary and succeeds.
    write_artefact(out, "demo", {"a": np.zeros(10)}, config_digest="d")
    assert [p.name for p in tmp_path.iterdir()] == ["big.h5"]


def test_config_digest_is_stable_and_sensitive():
    a = config_digest({"x": 0.1, "y": [1, 2], "z": {"b": 1, "a": 2}})
    b = config_digest({"z": {"a": 2, "b": 1}, "y": (1, 2), "x": 0.1})
    assert a == b and len(a) == 16
    assert config_digest({"x": 0.1}) != config_digest({"x": 0.1000001})


def test_write_json_refuses_nan(tmp_path):
    with pytest.raises(ValueError):
        write_json(tmp_path / "m.json", {"x": float("nan")})
    assert not (tmp_path / "m.json").exists()
    write_json(tmp_path / "m.json", {"b": 1, "a": [0.5]})
    assert (tmp_path / "m.json").read_text() == '{\n  "a": [\n    0.5\n  ],\n  "b": 1\n}\n'


def test_lineage_is_recorded_and_mismatched_inputs_are_refused(tmp_path):
    from mogaf.artefact import read_lineage, stage_inputs

    scene = write_artefact(tmp_path / "scene.h5", "ingest", {}, config_digest="scene-a")
    other_scene = write_artefact(tmp_path / "other.h5", "ingest", {}, config_digest="scene-b")
    with stage_inputs(scene):
        split = write_artefact(tmp_path / "split.h5", "split", {}, config_digest="r0.6")
    with stage_inputs(scene, split):
        priors = write_artefact(tmp_path / "priors.h5", "priors", {}, config_digest="p")
    lin = read_lineage(priors)
    assert lin.inputs == {"ingest": (read_lineage(scene).digest,), "split": (read_lineage(split).digest,)}
    # one lineage: same configs give the same digest (determinism), another upstream config another digest
    with stage_inputs(scene, split):
        again = write_artefact(tmp_path / "priors2.h5", "priors", {}, config_digest="p")
    assert read_lineage(again).digest == lin.digest
    with pytest.raises(MogafError, match=r"split\.h5: was made from another 'ingest' artefact than .*other\.h5"):
        with stage_inputs(other_scene, split):  # a split of one scene read with another scene
            pass
    with pytest.raises(MogafError, match=r"priors\.h5: was made from another 'split' artefact"):
        with stage_inputs(
            scene, tmp_path / "priors.h5", write_artefact(tmp_path / "split9.h5", "split", {}, config_digest="r0.9")
        ):
            pass
    # the same settings with other contents (a stage rerun on another machine or GPU): another lineage
    with stage_inputs(scene, split):
        rerun = write_artefact(tmp_path / "priors3.h5", "priors", {"depth": np.ones(3)}, config_digest="p")
        again_rerun = write_artefact(tmp_path / "priors4.h5", "priors", {"depth": np.ones(3)}, config_digest="p")
        changed = write_artefact(tmp_path / "priors5.h5", "priors", {"depth": np.full(3, 2.0)}, config_digest="p")
    assert read_lineage(rerun).digest == read_lineage(again_rerun).digest != read_lineage(changed).digest
    with stage_inputs(scene, split, rerun):
        recon = write_artefact(tmp_path / "recon.h5", "recon", {}, config_digest="r")
    with pytest.raises(MogafError, match=r"recon\.h5: was made from another 'priors' artefact than .*priors5\.h5"):
        with stage_inputs(changed, recon):
            pass
    # an artefact written outside any stage records no inputs and is never refused for it
    plain = write_artefact(tmp_path / "plain.h5", "priors", {}, config_digest="p")
    assert read_lineage(plain).inputs == {}
    with stage_inputs(other_scene, plain):
        pass


def test_output_that_cannot_be_written_is_one_line_naming_it(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    for write in (lambda p: write_json(p, {}), lambda p: write_artefact(p, "demo", {}, config_digest="d")):
        with pytest.raises(MogafError, match=r"file/sub/out: cannot be written"):
            write(blocker / "sub" / "out")
    assert blocker.read_text() == ""


def test_a_key_error_of_the_callers_own_code_is_not_blamed_on_the_file(tmp_path):
    path = _write(tmp_path / "x.h5")
    with pytest.raises(KeyError, match="mine"):
        with open_artefact(path, "demo"):
            {}["mine"]
