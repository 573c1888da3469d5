"""The learner's faster update (issue 22) against the pre-issue-22 code with the same weights.

Pure torch, small sizes; no timing assertions (timings live in ``mixed_traffic.bench``).
Tolerances: outputs within 1e-5, gradients within 1e-4 of each tensor's largest entry.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.bench_learner import _ReferenceGRU, random_batches, reference_learner
from agents.checkpoint import load_checkpoint
from agents.learning.rbpdqn import RBPDQN, LearnerConfig
from agents.nets.lca import HistoryGRU, LCAConfig

CHECKPOINT = Path(__file__).resolve().parents[1] / "agents" / "checkpoints" / "auto.pt"


def _assert_grads_close(got: list[torch.Tensor], want: list[torch.Tensor]) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        scale = w.abs().max().clamp_min(1e-12)
        assert ((g - w).abs().max() / scale).item() < 1e-4


def _grads(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.grad.clone() for p in module.parameters()]


def test_history_gru_matches_the_slicing_reference() -> None:
    torch.manual_seed(0)
    gru = HistoryGRU(12, 32)
    ref = _ReferenceGRU(12, 32)
    ref.load_state_dict(gru.state_dict())
    x = torch.randn(9, 5, 12)
    out, want = gru(x), ref(x)
    torch.testing.assert_close(out, want, atol=1e-6, rtol=0)
    out.square().sum().backward()
    want.square().sum().backward()
    _assert_grads_close(_grads(gru), _grads(ref))


def test_update_matches_the_reference_learner() -> None:
    """A few updates of the fast learner and of the pre-issue-22 code from the same weights."""
    cfg = LCAConfig()
    fast, ref = RBPDQN(cfg, seed=6), reference_learner(cfg, LearnerConfig(), seed=6)
    for batch in random_batches(cfg, 32, 3, seed=7):
        out_fast, out_ref = fast.update(batch), ref.update(batch)
        for k, v in out_ref.items():
            assert out_fast[k] == pytest.approx(v, rel=1e-4, abs=1e-6), k
    for a, b in zip(fast.critic_targ.parameters(), ref.critic_targ.parameters(), strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=0)


def test_shipped_checkpoint_loads_strictly_and_trains() -> None:
    learner, _ = load_checkpoint(CHECKPOINT)
    sd = torch.load(CHECKPOINT, weights_only=True)["learner"]
    for net in ("actor", "critic", "actor_targ", "critic_targ"):
        mine = getattr(learner, net).state_dict()
        assert {k: v.shape for k, v in mine.items()} == {k: v.shape for k, v in sd[net].items()}
    for opt in (learner.actor_opt, learner.critic_opt):
        assert all(g["fused"] for g in opt.param_groups)  # restored after the saved flags
    out = learner.update(random_batches(learner.lca_cfg, 16, 1)[0])
    assert all(np.isfinite(v) for v in out.values())


@pytest.mark.skipif(
    shutil.which("g++") is None and shutil.which("c++") is None,
    reason="torch.compile (inductor) needs a C++ compiler",
)
def test_compiled_update_matches_eager_and_is_deterministic() -> None:
    """``compile=True`` (torch.compile of the module-path losses): same maths, same bits twice,
    same checkpoint keys. Compiling takes a while (seconds with a warm inductor cache)."""
    cfg = LCAConfig()
    batches = random_batches(cfg, 16, 2, seed=10)
    runs = []
    for compile in (False, True, True):
        learner = RBPDQN(cfg, seed=11, compile=compile)
        outs = [learner.update(b) for b in batches]
        targ = [p.detach().clone() for p in learner.critic_targ.parameters()]
        runs.append((outs, targ, learner))
    for k, v in runs[0][0][-1].items():
        assert runs[1][0][-1][k] == pytest.approx(v, rel=1e-4, abs=1e-6), k
    for a, b in zip(runs[0][1], runs[1][1], strict=True):  # τ-scaled: Adam's ±lr steps damped
        torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
    assert runs[1][0] == runs[2][0]
    for a, b in zip(runs[1][1], runs[2][1], strict=True):
        assert torch.equal(a, b)
    assert runs[1][2].state_dict().keys() == runs[0][2].state_dict().keys()
    for net in ("actor", "critic"):
        assert runs[1][2].state_dict()[net].keys() == runs[0][2].state_dict()[net].keys()
