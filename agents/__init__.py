"""The AUTO agent (paper §IV-C/D/F), its training, and the rule-based drivers. Submodules are
imported explicitly (torch is heavy):

- ``agents.nets``: ``lca`` (``LCAConfig``, the LCA encoder), ``networks`` (``Actor``,
  ``Critic``, ``select``: masked argmax), ``fused`` (fused actor + critic inference).
- ``agents.learners``: ``rbpdqn`` (``RBPDQN``: losses and updates; batched ``Policy``),
  ``variants`` (P-DDPG, Q-PAMDP, imitation), ``replay`` (``ReplayBuffer``).
- ``agents.collection``: ``workers`` (``RolloutWorker``: env + local policy + local buffer),
  ``intervals`` (one transition per decision).
- ``agents.training``: ``config`` (``TrainConfig``), ``collectors`` (process / Ray rollout
  collectors), ``curves``, ``commit``, ``trainer`` (``Trainer``; the CLI is
  ``python -m mixed_traffic.train``), ``fleet_search`` (the evolution-strategies tool of
  ``python -m mixed_traffic.experiments.fleet``; no shipped policy comes from it).
- ``agents.driver``: ``Driver`` (the decision interval and the residual form on ACC-LC).
- ``agents.rules``: ``acc_lc`` (the ACC-LC baseline, ``AccLcPolicy``; ``plan`` exposes its
  checks), ``safety`` (``SafetyModule`` behind the learned policy), ``obs_batch``.
- ``agents.policies``: policies by name (``auto``, ``auto-raw``, ``acc-lc``, ``random``, ...).
- ``agents.checkpoint``: ``save_checkpoint`` / ``load_checkpoint`` / ``load_nets`` /
  ``load_policy`` / ``load_driver``.
- ``agents.bench_inference``: ``avg_inference_us`` (AvgIT per decision).

Policies see the env only through its public interface: ``mixed_traffic.env.api`` and
``mixed_traffic.config``. What differs from the paper, and why: ``docs/agent.md``.
"""
