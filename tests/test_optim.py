"""mogaf.optim: torch's Adam and deterministic switch without torch's compiler imports."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from mogaf.optim import Adam, use_deterministic_algorithms


def _train(opt_class, steps: int, resume_at: int | None = None):
    """A small regression trained with two param groups, weight decay and a
    cosine schedule; with `resume_at`, the optimiser is rebuilt there from
    its state_dict (as a resumed reconstruction does)."""
    gen = torch.Generator().manual_seed(3)
    net = torch.nn.Sequential(torch.nn.Linear(6, 16), torch.nn.Tanh(), torch.nn.Linear(16, 3))
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.3)
    x = torch.randn(64, 6, generator=gen)
    y = torch.randn(64, 3, generator=gen)

    def build():
        return opt_class(
            [{"params": net[0].parameters(), "lr": 3e-2}, {"params": net[2].parameters(), "lr": 1e-2}],
            weight_decay=1e-3,
            eps=1e-15,
        )

    opt = build()
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps, eta_min=1e-4)
    for step in range(steps):
        if step == resume_at:
            state = opt.state_dict()
            opt = build()
            opt.load_state_dict(state)
            sched.optimizer = opt
        loss = ((net(x) - y) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
    return [p.detach().clone() for p in net.parameters()], opt


@pytest.mark.parametrize("resume_at", [None, 17])
def test_adam_equals_torch_adam_bit_for_bit(resume_at):
    ours, opt = _train(Adam, 40, resume_at)
    reference, ref_opt = _train(torch.optim.Adam, 40, resume_at)
    assert all(torch.equal(a, b) for a, b in zip(ours, reference, strict=True))
    for p_ours, p_ref in zip(
        (p for g in opt.param_groups for p in g["params"]),
        (p for g in ref_opt.param_groups for p in g["params"]),
        strict=True,
    ):
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(opt.state[p_ours][key], ref_opt.state[p_ref][key]), key


def test_adam_step_leaves_autograd_as_it_was():
    p = torch.nn.Parameter(torch.ones(3))
    opt = Adam([p], lr=0.1)
    p.sum().backward()
    opt.step()
    assert torch.is_grad_enabled()
    assert not p.grad_fn and p.requires_grad  # updated in place, still a leaf


def test_deterministic_switch_sets_and_restores_the_flags():
    before = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
    try:
        use_deterministic_algorithms(True, warn_only=True)
        assert torch.are_deterministic_algorithms_enabled()
        assert torch.is_deterministic_algorithms_warn_only_enabled()
        use_deterministic_algorithms(False)
        assert not torch.are_deterministic_algorithms_enabled()
    finally:
        use_deterministic_algorithms(before[0], warn_only=before[1])


TRAINING_WITHOUT_COMPILER = """
import sys
import torch
from mogaf.forecast.base import torch_determinism
from mogaf.optim import Adam
p = torch.nn.Parameter(torch.ones(4))
with torch_determinism(0, 1):
    assert torch.are_deterministic_algorithms_enabled()
    opt = Adam([p], lr=0.1)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=3)
    for _ in range(3):
        opt.zero_grad(set_to_none=True)
        (p ** 2).sum().backward()
        torch.nn.utils.clip_grad_norm_([p], 1.0)
        opt.step()
        sched.step()
    opt.load_state_dict(opt.state_dict())
loaded = sorted(m for m in ("torch._dynamo", "torch._inductor") if m in sys.modules)
print(",".join(loaded) or "none")
"""


def test_training_imports_no_compiler():
    """A stage that trains with Adam under torch_determinism loads neither
    torch._dynamo nor torch._inductor (about a second of every process)."""
    res = subprocess.run([sys.executable, "-c", TRAINING_WITHOUT_COMPILER], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == "none"


# roma's three uses in the pipeline, with a gradient through the Procrustes
# solve; prints a digest of every result and which compiler modules loaded.
ROMA_USES = """
import hashlib, sys
if sys.argv[1] == "plain":
    import roma  # roma's own import, which loads torch._dynamo
import numpy as np
import torch
from mogaf.recon.init_tracks import rigid_fit
from mogaf.representation import matrix_to_quat
from mogaf.rigid import weighted_procrustes

gen = torch.Generator().manual_seed(0)
src = torch.randn(4, 30, 3, generator=gen, dtype=torch.float64)
dst = (src + 0.05 * torch.randn(4, 30, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
R, t = weighted_procrustes(src, dst)
(R.sum() + t.sum()).backward()
Rf, tf = rigid_fit(src[0].numpy(), dst[0].detach().numpy(), np.linspace(0.5, 1.5, 30))
q = matrix_to_quat(R.detach().float())
digest = hashlib.sha256()
for a in (R.detach().numpy(), t.detach().numpy(), dst.grad.numpy(), Rf, tf, q.numpy()):
    digest.update(np.ascontiguousarray(a).tobytes())
loaded = sorted(m for m in ("torch._dynamo", "torch._inductor") if m in sys.modules)
print(digest.hexdigest(), ",".join(loaded) or "none", "_dynamo" in vars(torch) and "torch._dynamo" not in sys.modules)
"""


def test_roma_without_the_compiler_gives_the_same_bits():
    """The pipeline's roma (mogaf.eager_roma) loads no compiler, leaves no
    stand-in on torch, and computes every result and gradient bit for bit as
    roma imported the plain way."""
    runs = {}
    for how in ("eager", "plain"):
        res = subprocess.run([sys.executable, "-c", ROMA_USES, how], capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr[-2000:]
        runs[how] = res.stdout.split()
    assert runs["eager"][1:] == ["none", "False"]
    assert "torch._dynamo" in runs["plain"][1].split(",")
    assert runs["eager"][0] == runs["plain"][0]


def test_a_roma_that_needs_more_of_the_compiler_is_imported_the_plain_way(tmp_path):
    (tmp_path / "roma").mkdir()
    (tmp_path / "roma" / "__init__.py").write_text(
        "import torch\nfrom . import parts\nIS_COMPILING = torch._dynamo.is_compiling\n"
    )
    (tmp_path / "roma" / "parts.py").write_text("import torch\nEAGER = torch._dynamo.disable(len)\n")
    code = (
        "import sys, torch\nfrom mogaf.eager_roma import load\nroma = load()\n"
        "print(roma.__file__ == sys.argv[1], roma.parts.EAGER is not len, 'torch._dynamo' in sys.modules,"
        " type(torch._dynamo).__name__)"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "roma" / "__init__.py")],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(tmp_path)},
    )
    assert res.returncode == 0, res.stderr[-2000:]
    # the second, plain import ran: roma.parts holds the real compiler's wrapper, not the stand-in's function
    assert res.stdout.split() == ["True", "True", "True", "module"]
