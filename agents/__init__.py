"""AUTO agent (paper §IV-C/D/F, DESIGN §10). Submodules are imported explicitly (torch is heavy):

- ``agents.nets.lca``: ``LCAConfig`` (z, m, d, ablation flags), ``LCA`` encoder.
- ``agents.nets.networks``: ``Actor``, ``Critic``, ``select`` (masked argmax; all-masked → follow).
- ``agents.learning.rbpdqn``: ``RBPDQN`` learner (``update(batch) -> losses``; ``regularize=False`` is
  BP-DQN), ``Policy`` (batched ``act`` for all agents of a step).
- ``agents.nets.fused``: fused actor + critic inference, numerically equal to the modules.
- ``agents.learning.replay``: ``ReplayBuffer`` (numpy SoA ring, resumable).
- ``agents.checkpoint``: ``save_checkpoint`` / ``load_checkpoint`` / ``load_policy``.
- ``agents.bench_inference``: ``avg_inference_us`` (AvgIT per decision).
- ``agents.collection.workers``: ``RolloutWorker`` (env + local policy + LocalBuffer), ``SharedWeights``.
- ``agents.learning.trainer``: ``TrainConfig``, ``Trainer`` (learner + GlobalBuffer; process/Ray workers);
  the CLI is ``python -m mixed_traffic.train``.
- ``agents.rules.acc_lc``: the ACC-LC baseline (``AccLcPolicy``; ``plan`` exposes its checks).
- ``agents.rules.safety``: ``SafetyModule``, the safety module behind the learned policy.
- ``agents.policies``: policies by name (``auto``, ``auto-raw``, ``acc-lc``, ``random``).

Deviations from the paper, and why:

- Training starts from ACC-LC demonstrations (``TrainConfig.demo_steps``, default 20 000
  transitions, split over the workers, switching to the learned policy mid-episode once met),
  and a small share of later episodes (``demo_share`` = 5 %) is still driven by ACC-LC. The paper
  trains from scratch; with the behaviour-cloning term the actor then starts from a safe driver
  instead of a random one (random driving ends almost every AV trip in a collision), and the
  replay keeps some safe examples. ``--demo-steps 0 --demo-share 0`` restores the paper.
- Learning from the demonstrations (DQfD, Hester et al. 2018): the critic also gets a
  large-margin loss on demonstrated decisions (``LearnerConfig.demo_margin``/``demo_weight``),
  because Q of decisions the demonstrator never took is otherwise pure extrapolation and the
  argmax picks them; and ``--pretrain-updates`` runs updates on the demonstrations alone, with
  the actor on behaviour cloning only (α = 0), before the learned policy drives.
- Expert relabelling (DAgger, Ross et al. 2011; ``TrainConfig.expert_labels``, on by default):
  every transition the learned policy drives also stores ACC-LC's action for the same
  observation, and the BC term and the DQfD margin target that label instead of the taken
  action. Cloning only the demonstrator's states compounds errors: the pretrained actor
  matched ACC-LC to 0.45° of steering on held-out demonstration states but was off by 3-5°
  on the states it drove into itself, and 82-100 % of its AV trips ended in a collision or
  off the road. ``--no-expert-labels`` restores BC on the taken action.
- The shipped checkpoint was trained with α = 0 (``--alpha 0``): the actor is the relabelled
  BC fit and RL shapes the decisions through the critic (TD + margin). With α = 0.6 the
  normalised Q term outweighed the steering precision the BC term asks for, and the RL
  fine-tune diverged (critic loss 30-300 within ~1000 updates; measured before relabelling).
  It was then fine-tuned from those weights (``--init``) with accel_brake errors weighted 10
  in the BC term (``--bc-accel-weight 10``; the paper weights both parameters equally): with
  weight 1 the actor's accel_brake was 0.3-0.45 m/s² below ACC-LC's label on its own states.
  Much of that came from ACC-LC itself: its emergency term switched on at one threshold, so
  in steady following sensor noise flipped it between +0.6 and -2.5 m/s² every few steps, and
  the fit could only blur the switch. After the term was blended in, the network was
  fine-tuned twice more on the new labels (``--init``): once on the default weather mix, then
  with normal weather in 2/3 of the episodes (``--weathers`` with ``normal`` listed six times).
  The network cannot tell the weather from its inputs well, and with the uniform mix its
  accel_brake was on average 0.17 m/s² below the label in normal weather (0.02 in rain and
  fog); after the normal-heavy fine-tune it was 0.04 m/s² above in normal weather and 0.15 above
  in rain (merge-ramp, p = 1.0). The fit still shrinks towards the mean (it accelerates less
  than ACC-LC where ACC-LC accelerates, and brakes less where it brakes), most where a queue
  starts: the network cannot tell holding from going and fits the mean of the two.
- The last four fine-tunes fit accel_brake as an upper expectile of the label instead of its
  mean (``--bc-accel-expectile`` 0.7, then 0.8 three times: errors below the label weigh 2τ,
  above it 2(1 − τ)). Behind the safety module, which clamps the acceleration where ACC-LC brakes,
  erring upwards caused no terminal event in the eval cells, and AUTO starts queues sooner; the
  network alone still has terminal events on the bottleneck and urban variants (README).
- A safety module (``agents.rules.safety``) sits behind the learned policy at evaluation: the paper
  names it as standard in industrial stacks (§VI) but evaluates AUTO without one. It hands the
  step to ACC-LC when the learned steering would leave the lane corridor (or enter a gap ACC-LC
  rejects) or drift off the lane centre beyond ACC-LC's steering, and in a lane that must be
  left; when ACC-LC brakes, it clamps the learned acceleration to at most ACC-LC's + 0.3 m/s².
  Without it the network ends a share of its AV trips in a terminal event on the bottleneck
  and urban eval variants (README). ``auto-raw`` is the policy without it; the
  ``sm_share`` metric reports how often the module changed an action. Training does not use it.
- The behaviour-cloning term weights steering errors by ``bc_steer_weight`` = 100: steering
  ±1 is ±60°, lane keeping needs about 1°, and with equal weights the fit ignores steering.
  Exploration noise on steering is scaled down by ``STEER_NOISE_FACTOR`` for the same reason.
- Per-worker exploration follows the Ape-X ladder (ε and σ shrink geometrically over the
  workers); the paper only says "different random noises".
- Learner update ratio is fixed (updates per transition received, back-pressure on the workers
  when the learner lags) rather than "update as fast as possible"; ``--update-ratio 0`` gives
  the latter.
- Actor loss: the BC term is *added* (TD3+BC, the paper's cited source); the printed equation
  negates it too, which would push the actor away from the data.
- LCA's fusion also takes the ego embedding: E_s = W8(E_k-1 ⊕ E_k ⊕ E_k+1 ⊕ h_A)
  (``LCAConfig.ego_fusion``, on by default). In the paper's equation h_A is only the attention
  query, so the agent's own speed, heading and lateral offset reach the actor only through at
  most three softmax weights per lane; ACC-LC's acceleration depends on the ego speed directly.
  Cloning ACC-LC from random weights on one run's replay (lr 1e-3, 12.5 k updates, one seed),
  the held-out BC loss was 0.89 against 1.01 in the paper's form, lower at every checkpoint.
  The shipped network is the first with it (README).
  ``--no-ego-fusion`` trains the paper's form; checkpoints written before the field load in it,
  and ``--init`` widens them with zero weights on h_A, so a fine-tune starts from the same policy.
- A lane whose nodes are all masked contributes a zero vector to the fusion (softmax over an
  empty set is undefined); the paper does not say.
- MLP depths (not given in the paper): fusion Linear(3D + D, D)+ReLU (3D in the paper's
  form); actor head D→D→6;
  critic head 2D→D→3; D = 32 everywhere (D1 = D2 = D3 = D4).
- NoSTAR: one residual masked self-attention layer over [ego, 9 nodes], then the same
  lane-wise read-out; NoLANE: one ego attention over all 9 nodes, fusion of that one vector.
"""
