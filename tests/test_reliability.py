"""A reconstruction killed mid-training (SIGTERM, SIGKILL) leaves no artefact,
resumes from its checkpoint, and ends identical to an uninterrupted run.

The whole-pipeline version (Snakemake killed during recon, then rerun) is in
test_pipeline.py; corrupted artefacts are refused in test_artefact.py.
"""

from __future__ import annotations

import json
import logging
import signal
import subprocess
import sys
import time

import pytest

from mogaf.recon.stage import run_recon_stage
from support.tiny_scene import TINY_PARAMS, assert_same_arrays, make_tiny_scene

# about 15 s with two workers: collected early (tests/conftest.py)
pytestmark = pytest.mark.long(seconds=15)

PARAMS = {**TINY_PARAMS, "iterations": 150, "checkpoint_every": 5}

CHILD = """
import json, sys
from mogaf.recon.stage import run_recon_stage
a = json.loads(sys.argv[1])
run_recon_stage(a["scene"], a["split"], a["priors"], a["out"], a["params"], seed=0, checkpoint=a["checkpoint"],
                progress=False)
"""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("kill")
    scene, split, priors = make_tiny_scene(folder)
    reference = run_recon_stage(scene, split, priors, folder / "reference.h5", PARAMS, seed=0, progress=False)
    return folder, scene, split, priors, reference


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "SIGKILL"])
def test_killed_recon_resumes_to_identical_result(tiny, sig, caplog):
    folder, scene, split, priors, reference = tiny
    work = folder / sig.name
    work.mkdir()
    out, checkpoint = work / "recon.h5", work / "recon.pt"
    args = {
        "scene": str(scene),
        "split": str(split),
        "priors": str(priors),
        "out": str(out),
        "params": PARAMS,
        "checkpoint": str(checkpoint),
    }
    proc = subprocess.Popen([sys.executable, "-c", CHILD, json.dumps(args)], stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not checkpoint.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before its first checkpoint: " + proc.stderr.read().decode()[-2000:]
    proc.send_signal(sig)
    proc.wait(timeout=60)
    assert proc.returncode == -sig
    assert not out.exists()
    assert sorted(p.name for p in work.iterdir()) == ["recon.pt"]  # no temporary file either
    with caplog.at_level(logging.INFO, logger="mogaf.recon.stage"):
        run_recon_stage(scene, split, priors, out, PARAMS, seed=0, checkpoint=checkpoint, progress=False)
    assert any("resumed from" in r.getMessage() for r in caplog.records)
    assert not checkpoint.exists()
    assert_same_arrays(reference, out)
