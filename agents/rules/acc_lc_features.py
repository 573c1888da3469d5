"""ACC-LC's view of the observation: the stacked observation decoded into SI features.

:func:`features` returns a dict of (A, ...) arrays (the layout of DESIGN §6, normalisation
constants of ``mixed_traffic.sensing.observation`` via ``mixed_traffic.env.api``):

Lengths (``len``, ``vlen``, ``h_len``) that fill the observation's 10 m scale are read as
``AccLcConfig.long_length``: the vehicle is at least that long, and its rear may be far behind.

- ego: ``v``, ``h`` (heading), ``len``, ``wid``, ``d`` (lateral offset), ``vlat_hist`` (lateral
  velocity from the offset history, unwrapped across lane switches), ``v_mean`` (speed over
  the observed history frames);
- waypoints: ``wp_speed``, ``wp_orient`` (A, 3, m);
- speed-limit preview (A, 3, k): ``pv_dist`` [m] (inf = none) and ``pv_speed`` [m/s] of the
  drops ahead (k = 0 for an observation without ``limits``);
- neighbours of the latest frame (A, 3, 2: lane column x front/rear): ``present``, ``vdist``,
  ``vrel``, ``vlen``, ``vwid``, ``vlat``;
- front vehicles of the last frames since the last lane switch (A, 3, K): ``h_dist`` (extrapolated
  to now), ``h_rel``, ``h_len``, ``h_wid``, ``h_lat``;
- ``exists`` (A, 3) lanes, ``mask`` (A, 3) allowed decisions, ``light`` (A, 3) majority state
  (0 red, 1 yellow, 2 green, -1 none) and ``light_dist`` (A, 3), ``signal_dist`` (A,) [m] to
  the HD map's next signal on the current lane's route (inf = none or no ``signals`` key).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from agents.rules import acc_lc_features_kernel
from agents.rules.acc_lc_config import LANE_C as _C
from agents.rules.acc_lc_config import AccLcConfig
from mixed_traffic import compiled
from mixed_traffic.env.api import CURVATURE_WINDOW, EGO_SCALE, SPEED_SCALE, WAYPOINT_SCALE

_KEYS = ("v", "h", "len", "wid", "d", "v_mean", "vlat_hist", "wp_speed", "wp_orient", "pv_dist",
         "pv_speed", "present", "vdist", "vrel", "vlen", "vwid", "vlat", "h_dist", "h_rel",
         "h_len", "h_wid", "h_lat", "exists", "mask", "light", "light_dist", "signal_dist",
         "give_way")  # fmt: skip
"""The keys of :func:`features`, in its order (the kernel's outputs)."""
_OPTIONAL = ("limits", "signals", "give_way")
"""Keys an older observation lacks (:func:`features` then runs the numpy stages)."""


def lane_curvature(f: Mapping[str, np.ndarray]) -> np.ndarray:
    """(A,) curvature of the current lane where the ego is [1/m, + = left], from the waypoint
    orientations (``AccLcPolicy._features``) over the env's ``CURVATURE_WINDOW``; 0 where the
    lane is missing."""
    o = f["wp_orient"][:, _C]
    w = min(CURVATURE_WINDOW, o.shape[1] - 1)
    kappa = (o[:, w] - o[:, 0]) / max(w, 1)
    return np.where(f["exists"][:, _C], kappa, 0.0)


def features(ob: Mapping[str, np.ndarray], c: AccLcConfig) -> dict[str, np.ndarray]:
    """Stacked observation ``ob`` (A, ...) per key -> the SI features of the module docstring;
    compiled (:mod:`agents.rules.acc_lc_features_kernel`) unless ``compiled.enabled()`` is off
    or the observation is an older one (without the ``_OPTIONAL`` keys)."""
    ego = ob["ego"]
    fast = compiled.enabled() and len(ego) and np.shape(ego)[1] >= 2
    if fast and all(k in ob for k in _OPTIONAL):
        return _features_compiled(ob, c)
    return _features_reference(ob, c)


def _features_compiled(ob: Mapping[str, np.ndarray], c: AccLcConfig) -> dict[str, np.ndarray]:
    """:func:`_features_reference` in one kernel."""
    arrays = [np.asarray(ob[k]) for k in ("ego", "lanes", "vehicles", "lights", "node_mask",
                                          "action_mask", "limits", "signals", "give_way")]  # fmt: skip
    out = acc_lc_features_kernel.decode(
        *arrays, c.dt, c.long_length, c.preview_range, c.camera_range, EGO_SCALE,
        WAYPOINT_SCALE, _neighbour_scale(c), SPEED_SCALE,
    )  # fmt: skip
    return dict(zip(_KEYS, out))


def _features_reference(ob: Mapping[str, np.ndarray], c: AccLcConfig) -> dict[str, np.ndarray]:
    """The numpy reference of :func:`features`."""
    ego = np.asarray(ob["ego"], np.float64)  # (A, z, 5)
    lanes = np.asarray(ob["lanes"], np.float64)  # (A, 3, z, 4m)
    veh = np.asarray(ob["vehicles"], np.float64)  # (A, 3, z, 12)
    lights = np.asarray(ob["lights"], np.float64)  # (A, 3, z, 4)
    A = ego.shape[0]
    f, dh, valid = _ego_features(ego, c.dt)
    f["len"] = _length(ego[:, -1, 2], c)
    m = lanes.shape[-1] // 4
    wp = lanes[:, :, -1].reshape(A, 3, m, 4) * WAYPOINT_SCALE
    f["wp_speed"] = wp[..., 3]  # (A, 3, m)
    f["wp_orient"] = wp[..., 2]
    _preview_features(f, ob, c)
    scale = _neighbour_scale(c)
    _neighbour_features(f, veh, scale, A)
    _history_features(f, veh, scale, dh, valid, c.dt)
    f["vlen"] = _length(veh[:, :, -1].reshape(A, 3, 2, 6)[..., 3], c)
    K = f["h_len"].shape[-1]
    f["h_len"] = _length(veh[:, :, -K:, 3], c)
    nm = np.asarray(ob["node_mask"])
    f["exists"] = nm[:, :, 0] > 0
    f["mask"] = np.asarray(ob["action_mask"]) > 0
    _light_features(f, lights, c)
    # the HD map's next signal on the current lane's route (none in an older observation)
    sig = np.asarray(ob["signals"], np.float64)[:, 1] if "signals" in ob else np.zeros(A)
    f["signal_dist"] = np.where(sig > 0, sig * c.preview_range, np.inf)
    # an older observation has no give_way key: every line may then be one
    f["give_way"] = np.asarray(ob["give_way"])[:, 1] > 0 if "give_way" in ob else np.ones(A, bool)
    return f


def _neighbour_scale(c: AccLcConfig) -> np.ndarray:
    """(6,) scales of a neighbour's columns: distance, relative speed, heading, length, width,
    lateral offset."""
    return np.array([c.lidar_range, SPEED_SCALE, np.pi, EGO_SCALE[2], 5.0, 2.0])


def _length(norm: np.ndarray, c: AccLcConfig) -> np.ndarray:
    """Lengths [m] of normalised observed lengths (any shape); a full scale (the observation
    clips longer vehicles to it) reads as ``c.long_length``."""
    return np.where(norm >= 1.0 - 1e-6, c.long_length, norm * EGO_SCALE[2])


def _preview_features(f: dict[str, np.ndarray], ob: Mapping[str, np.ndarray], c: AccLcConfig
                      ) -> None:  # fmt: skip
    """``pv_dist`` and ``pv_speed`` of the ``limits`` key (none in an older observation)."""
    A = len(f["v"])
    lm = np.asarray(ob["limits"], np.float64) if "limits" in ob else np.zeros((A, 3, 0, 2))
    seen = lm[..., 1] > 0
    f["pv_dist"] = np.where(seen, lm[..., 0] * c.preview_range, np.inf)
    f["pv_speed"] = np.where(seen, lm[..., 1] * SPEED_SCALE, np.inf)


def _ego_features(
    ego: np.ndarray, dt: float
) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Ego features of the latest frame and ``vlat_hist`` (frames ``dt`` [s] apart); also the
    offset history ``dh`` [m] (A, z) and the ``valid`` frames (A, z) the neighbours need."""
    e = ego[:, -1] * EGO_SCALE
    f = {"v": np.maximum(e[:, 0], 0.0), "h": e[:, 1], "len": e[:, 2], "wid": e[:, 3]}
    f["d"] = e[:, 4]
    valid = ego[:, :, 2] > 0
    # the mean over the observed frames: in fog a frame's speed is read with 15 % noise
    speeds = np.maximum(ego[:, :, 0] * EGO_SCALE[0], 0.0)
    f["v_mean"] = np.where(valid, speeds, 0.0).sum(1) / np.maximum(valid.sum(1), 1)
    # lateral offset history, unwrapped across lane switches (jumps > 1.5 m)
    dh = ego[:, :, 4] * EGO_SCALE[4]
    k = max(0, ego.shape[1] - 3)
    diffs = np.diff(dh[:, k:], axis=1)
    ok = valid[:, k + 1 :] & valid[:, k:-1] & (np.abs(diffs) < 1.5)
    f["vlat_hist"] = np.where(ok, diffs, 0.0).sum(1) / np.maximum(ok.sum(1), 1) / dt
    return f, dh, valid


def _neighbour_features(
    f: dict[str, np.ndarray], veh: np.ndarray, scale: np.ndarray, A: int
) -> None:
    """Front and rear vehicle of each lane column in the latest frame (into ``f``; ``A``
    agents)."""
    vv = veh[:, :, -1].reshape(A, 3, 2, 6)
    vv = vv * scale
    present = vv[..., 4] > 0
    f["present"] = present
    f["vdist"] = np.where(present, vv[..., 0], np.array([np.inf, -np.inf]))
    f["vrel"] = vv[..., 1]
    f["vlen"] = vv[..., 3]
    f["vwid"] = vv[..., 4]
    f["vlat"] = vv[..., 5]


def _history_features(
    f: dict[str, np.ndarray],
    veh: np.ndarray,
    scale: np.ndarray,
    dh: np.ndarray,
    valid: np.ndarray,
    dt: float,
) -> None:
    """Front vehicles of the frames no older than 0.8 s (``dt`` [s] apart; at most 5) into
    ``f``. Object permanence: a leader hidden behind a nearer vehicle of the same
    lane, or gone into a junction lane the ego does not follow, is extrapolated from its last
    sighting, only since the last lane switch (older sightings, extrapolated seconds ahead,
    made the ego keep its distance from leaders long gone)."""
    A = dh.shape[0]
    K = min(veh.shape[2], 1 + int(0.8 / dt + 1e-9))
    hv = veh[:, :, -K:, :6] * scale  # (A, 3, K, 6)
    age = (K - 1 - np.arange(K)) * dt
    hp = hv[..., 4] > 0
    jump = np.abs(np.diff(dh[:, -K:], axis=1)) >= 1.5  # (A, K-1)
    since = np.flip(np.cumsum(np.flip(jump, 1), axis=1), 1) == 0  # no switch after k
    hvalid = np.concatenate([since, np.ones((A, 1), bool)], axis=1) & valid[:, -K:]
    hp &= hvalid[:, None, :]
    f["h_dist"] = np.where(hp, hv[..., 0] + hv[..., 1] * age, np.inf)
    f["h_rel"], f["h_len"] = hv[..., 1], hv[..., 3]
    f["h_wid"], f["h_lat"] = hv[..., 4], hv[..., 5]


def _light_features(f: dict[str, np.ndarray], lights: np.ndarray, c: AccLcConfig) -> None:
    """Light state per lane column, a majority of the last 3 frames with a detection, and its
    distance (the last detected one when the latest frame lost the light), into ``f``."""
    lt = lights[:, :, -3:]
    det = lt[..., :3].sum(-1) > 0.5
    votes = (lt[..., :3] > 0.5).sum(2)  # (A, 3, 3) counts of r/y/g
    state = np.where(det.any(2), votes.argmax(-1), -1)
    f["light"] = state
    f["light_dist"] = np.where(
        det[..., -1], lights[:, :, -1, 3] * c.camera_range, np.where(det.any(2), 0, np.inf)
    )
    # fall back to the last detected distance when the latest frame lost the light
    last = lights[:, :, -2, 3] * c.camera_range
    f["light_dist"] = np.where(~det[..., -1] & det.any(2), last, f["light_dist"])
