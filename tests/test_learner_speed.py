"""The learner's faster update (issue 22) against the pre-issue-22 code with the same weights.

Pure torch, small sizes; no timing assertions (timings live in ``mixed_traffic.bench``).
Tolerances: outputs within 1e-5, gradients within 1e-4 of each tensor's largest entry.
"""

from __future__ import annotations

import copy
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.bench_learner import _ReferenceGRU, random_batches, reference_learner
from agents.checkpoint import load_checkpoint
from agents.learners.rbpdqn import RBPDQN, LearnerConfig
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
    same checkpoint keys. One compile."""
    cfg = LCAConfig(z=2, m=2)  # a short history: a smaller graph to compile
    batches = random_batches(cfg, 16, 2, seed=10)
    eager, compiled = RBPDQN(cfg, seed=11), RBPDQN(cfg, seed=11, compile=True)
    start = copy.deepcopy(compiled.state_dict())

    def run(learner: RBPDQN) -> tuple[list, list]:
        outs = [learner.update(b) for b in batches]
        return outs, [p.detach().clone() for p in learner.critic_targ.parameters()]

    (want, want_targ), (got, got_targ) = run(eager), run(compiled)
    for k, v in want[-1].items():
        assert got[-1][k] == pytest.approx(v, rel=1e-4, abs=1e-6), k
    for a, b in zip(want_targ, got_targ, strict=True):  # τ-scaled: Adam's ±lr steps damped
        torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
    compiled.load_state_dict(start)  # the same compiled graphs again: the same bits
    again, again_targ = run(compiled)
    assert again == got and all(map(torch.equal, again_targ, got_targ))
    assert compiled.state_dict().keys() == eager.state_dict().keys()
    for net in ("actor", "critic"):
        assert compiled.state_dict()[net].keys() == eager.state_dict()[net].keys()
