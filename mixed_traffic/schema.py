"""Names, units and meanings of every reported metric, and the layout of a result record.

Pure data (no SUMO, no torch) so ``analysis`` can label tables and figures from result files.

A result record (one per episode, one JSON object per line in ``records.jsonl``)::

    {"cell": {"policy", "scenario", "density", "penetration", "weather", "detection_range", "seed"},
     "status": "ok" | "failed", "error": str | None,
     "config": EnvConfig.to_dict(), "seed": int, "sumo_version": str, "git_revision": str,
     "code": str (provenance.code_key), "created": ISO-8601 time, "wall_time": s,
     "warmup": s, "ring_length": m (a ring's circumference, else None),
     "metrics": {key: value for key in METRICS}}
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Metric:
    key: str
    label: str
    """Short name as in the paper (DESIGN §9)."""
    unit: str
    description: str
    better: str = ""
    """'lower', 'higher' or '' (no preference)."""
    nonnegative: bool = True
    """Never below 0 by construction (times, speeds, spreads, shares, counts): its 95 % interval is
    the log-scale one of :func:`analysis.results.nonneg_mean_ci`, else the Student t one."""


METRICS: dict[str, Metric] = {
    m.key: m
    for m in (
        Metric("dt_tf", "DT-TF", "s", "mean time of all vehicles to cross the 1 km measurement segment", "lower"),
        Metric("avg_dt_a", "AvgDT-A", "s/km", "AV driving time per km", "lower"),
        Metric("avg_at_c", "AvgAT-C", "s", "time the rear vehicle C slowed by > 0.1 m/s within a step, per AV trip", "lower"),
        Metric("avg_di_c", "AvgDI-C", "-", "delay index of rear vehicles: actual / free-flow travel time", "lower"),
        Metric("min_ttc_a", "MinTTC-A", "s", "minimum TTC of each AV over its trip, averaged over AVs", "higher"),
        Metric("avg_off_a", "AvgOFF-A", "m", "mean |lateral offset| from the centreline while following a lane", "lower"),
        Metric("avg_vel_a", "AvgVEL-A", "m/s", "mean AV speed", "higher"),
        Metric("avg_jerk_a", "AvgJERK-A", "m/s³", "mean |a_t - a_(t-1)| / dt of AVs", "lower"),
        Metric("avg_dec_c", "AvgDEC-C", "m/s", "mean speed drop of C within 1 s after an AV brakes or changes lane", "lower"),
        Metric("pt_rt", "PT-RT", "%", "share of AV time with TTC < 4 s", "lower"),
        Metric("avg_r", "AvgR", "-", "mean reward per AV action", "higher", nonnegative=False),
        Metric("avg_it", "AvgIT", "ms", "mean policy inference time per decision", "lower"),
        Metric("sm_share", "SM", "%", "share of AUTO's decisions the safety module changed", "lower"),
        Metric("measured_density", "density", "veh/km", "measured density in the measurement segment after warm-up"),
        Metric("mean_speed", "speed", "m/s", "mean speed of all vehicles in the measurement segment", "higher"),
        Metric("vehicles_crossed", "crossed", "veh", "vehicles that crossed the whole measurement segment"),
        Metric("speed_std", "speed std", "m/s", "standard deviation of all (vehicle, step) speeds in the measurement segment after warm-up", "lower"),
        Metric("fuel", "fuel", "l/100 km", "fuel of all vehicles per distance driven in the measurement segment after warm-up (SUMO's emission model; volume at the fuel's density, 742 g/l petrol)", "lower"),
        Metric("speed_std_ahead", "speed std ahead", "m/s", "speed std of the vehicles within av_window (200 m) ahead of each AV in its lane (half a ring at most), pooled over the steps after warm-up, mean over AVs weighted by samples", "lower"),
        Metric("speed_std_behind", "speed std behind", "m/s", "speed std of the vehicles within av_window (200 m) behind each AV in its lane (half a ring at most); below speed std ahead: the AVs leave a calmer wake", "lower"),
        Metric("flow", "flow", "veh/h/lane", "Edie's flow per lane in the measurement segment after warm-up"),
        Metric("wave_speed", "wave speed", "km/h", "speed of the stop-and-go waves in the measurement segment after warm-up, from the lag of the best cross-correlation of speed series 30-70 m apart; waves travel upstream (< 0) at 5-42 km/h; empty (no waves) when the speed patterns move downstream with the vehicles, faster than any wave could, inconsistently, or not at all", nonnegative=False),
        Metric("av_trips", "AV trips", "trips", "AV trips that ended (arrived or terminated)"),
        Metric("route_completion", "completion", "%", "share of ended AV trips that reached their destination", "higher"),
        Metric("collisions", "collisions", "count", "collisions (any vehicles)", "lower"),
        Metric("teleports", "teleports", "count", "SUMO teleports (should be 0)", "lower"),
        Metric("terminal_collision", "T-collision", "count", "AVs terminated by a collision", "lower"),
        Metric("terminal_off_road", "T-off-road", "count", "AVs terminated for leaving the road", "lower"),
        Metric("terminal_route_deviation", "T-route", "count", "AVs terminated for deviating from the route", "lower"),
        Metric("terminal_red_light", "T-red-light", "count", "AVs terminated for running a red light", "lower"),
        Metric("terminal_speed_limit", "T-speeding", "count", "AVs terminated for breaking the speed limit", "lower"),
    )
}  # fmt: skip

#: The paper's macroscopic and microscopic tables (Tables "Macroscopic/Microscopic Evaluation").
MACRO = ("avg_dt_a", "avg_at_c", "avg_di_c")
MICRO = ("min_ttc_a", "avg_off_a", "avg_vel_a", "avg_jerk_a", "avg_dec_c")
#: Traffic smoothing: travel time, the speed spread, fuel, and the waves ahead of / behind the AVs.
SMOOTHING = ("dt_tf", "speed_std", "fuel", "speed_std_ahead", "speed_std_behind")
SAFETY = (
    "collisions",
    "teleports",
    "terminal_collision",
    "terminal_off_road",
    "terminal_route_deviation",
    "terminal_red_light",
    "terminal_speed_limit",
    "route_completion",
)
TERMINAL_REASONS = ("collision", "off_road", "route_deviation", "red_light", "speed_limit")
CELL_KEYS = ("policy", "scenario", "density", "penetration", "weather", "detection_range", "seed",
             "copy")  # fmt: skip
"""What makes an episode's record its own: the condition, the seed and, in a batch of copies of
the scenario (``EnvConfig.copies``), its copy (0 without copies)."""
#: Subfolders of a sweep's results folder: the extra all-human cells of the fundamental diagram,
#: and the trajectories (``.npz``) of its representative cells.
FD_DIR = "fd"
TRACE_DIR = "trajectories"
BASELINES = ("transfuser", "drl-mf", "head", "bp-dqn", "p-ddpg", "q-pamdp")
"""The paper's baselines and RL-model comparisons (§V-A) besides ACC-LC: trained policies."""
ABLATIONS = ("auto-noimp", "auto-novec", "auto-nostar", "auto-nolane", "auto-nohis", "auto-nomul")
"""The paper's AUTO variants (§V-A): trained policies."""
STUDY_POLICIES = ("rbp-dqn", *BASELINES, *ABLATIONS)
"""Policies of ``python -m mixed_traffic.study``, each its own checkpoint in
agents/checkpoints/study/; rbp-dqn is AUTO's training pipeline at the study's budget."""
AUTO_POLICIES = ("auto", "auto-raw", "auto-mean", "auto-ring")
"""AUTO's checkpoint with the safety module, without it, and with its continuous parameters
replaced by their mean over a reference set of states (``runner.reference_u``); and the same
learner trained on the ring family alone (its own checkpoint, with the safety module)."""
LEARNED = (*AUTO_POLICIES, "ppo", "ppo-ring", *STUDY_POLICIES)
"""Policies that load a checkpoint."""
POLICIES = (
    *AUTO_POLICIES, "acc-lc", "acc-lc-tuned", "acc-lc-conservative", "idm", "random",
    "follower-stopper",
    "pi-saturation", "ppo", "ppo-ring", *STUDY_POLICIES,
)  # fmt: skip


def label(key: str) -> str:
    """'DT-TF (s)' style axis label of a metric."""
    m = METRICS[key]
    return f"{m.label} ({m.unit})" if m.unit not in ("-", "") else m.label
