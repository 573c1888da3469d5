"""Weather: sensor noise, shorter ranges and misdetected traffic lights (paper §V-I)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.config import SensorConfig
from mixed_traffic.sensing import sensing_kernel
from mixed_traffic.sensing.camera import NO_LIGHT
from mixed_traffic.sensing.frame import PerceptionFrame
from mixed_traffic.sensing.gnss import EGO_FEATURES
from mixed_traffic.sensing.lidar import VEHICLE_FEATURES

#: Additive noise floors per vehicle / ego feature (same units): noise std is
#: ``rel_noise * (|x| + floor)`` so features that are zero (relative speed, offset) still jitter.
VEHICLE_NOISE_FLOOR = np.array([1.0, 0.5, 0.02, 0.2, 0.1, 0.1])
EGO_NOISE_FLOOR = np.array([0.5, 0.02, 0.0, 0.0, 0.1])
#: Ego length and width are known exactly (own vehicle): noise multiplier per ego feature.
EGO_NOISY = np.array([1.0, 1.0, 0.0, 0.0, 1.0])


@dataclass(frozen=True)
class WeatherPreset:
    """Sensor degradation of one weather condition (paper §V-I: 3-18 % perturbation).

    A sensed continuous feature is ``x + rel_noise * (|x| + floor) * eps`` with eps ~ N(0, 1),
    i.e. its relative RMS error is ``rel_noise`` (floors: ``VEHICLE_NOISE_FLOOR``,
    ``EGO_NOISE_FLOOR``). A detected light shows one of the two wrong states (uniformly) with
    probability ``light_misdetect``. Detection ranges are multiplied by the range factors.
    """

    name: str
    rel_noise: float
    """Relative standard deviation of every perturbed feature [-]."""
    light_misdetect: float
    """Probability that a detected traffic light reports a wrong state [-]."""
    lidar_range_factor: float
    """Multiplier of ``SensorConfig.lidar_range`` [-]."""
    camera_range_factor: float
    """Multiplier of ``SensorConfig.camera_range`` [-]."""


WEATHER_PRESETS: dict[str, WeatherPreset] = {
    # clear day: residual sensor error only
    "normal": WeatherPreset("normal", 0.03, 0.02, 1.0, 1.0),
    # rain: wet-road LiDAR returns and lens droplets; paper's 13 % light error rate
    "rain": WeatherPreset("rain", 0.08, 0.13, 0.9, 0.85),
    # fog: strongest perturbation and shortest ranges
    "fog": WeatherPreset("fog", 0.15, 0.18, 0.6, 0.5),
    # night: LiDAR is active (small loss), the camera loses contrast
    "night": WeatherPreset("night", 0.06, 0.08, 0.95, 0.7),
}


def noise_draws(rng: np.random.Generator, a: int) -> tuple[np.ndarray, ...]:
    """Every random number ``_degrade`` uses for ``a`` agents, in the order it draws them:
    vehicle and ego feature noise, light misdetection (uniform, state shift), light distance."""
    return (
        rng.standard_normal((a, 3, 2, len(VEHICLE_FEATURES))),
        rng.standard_normal((a, len(EGO_FEATURES))),
        rng.random((a, 3)),
        rng.integers(1, 3, size=(a, 3)),
        rng.standard_normal((a, 3)),
    )


def degrade(
    truth: PerceptionFrame, weather: WeatherPreset, sensors: SensorConfig, rng: np.random.Generator
) -> PerceptionFrame:
    """The sensed frame: ``truth`` with the weather's ranges, noise and light misdetection."""
    w = weather
    draws = noise_draws(rng, len(truth.neighbours.lane))
    if compiled.enabled():
        return _degrade_compiled(truth, w, sensors, draws)
    z_veh, z_ego, u_light, shift, z_ldist = draws
    cut = within_range(truth, sensors, w.lidar_range_factor, w.camera_range_factor)
    seen = cut.neighbours.vehicle >= 0
    # veh + rel_noise * (|veh| + floor) * N(0, 1), evaluated in place (the same roundings)
    noise = np.abs(truth.vehicles)
    noise += VEHICLE_NOISE_FLOOR
    noise *= w.rel_noise
    noise *= z_veh
    noise += truth.vehicles
    veh = np.where(seen[..., None], noise, 0.0)
    dist = np.where(seen, veh[..., 0], cut.neighbours.distance)
    ego = truth.ego + EGO_NOISY * w.rel_noise * (np.abs(truth.ego) + EGO_NOISE_FLOOR) * z_ego
    # traffic lights: wrong states, noisy distances
    state = cut.light_state
    wrong = (state != NO_LIGHT) & (u_light < w.light_misdetect)
    state = np.where(wrong, (state + shift) % 3, state).astype(np.int8)
    ldist = truth.light_dist * (1.0 + w.rel_noise * z_ldist)
    ldist = np.where(state != NO_LIGHT, np.maximum(ldist, 0.0), np.inf)
    return PerceptionFrame(replace(cut.neighbours, distance=dist), veh, ego, state, ldist,
                           truth.give_way)  # fmt: skip


def within_range(
    truth: PerceptionFrame, sensors: SensorConfig, lidar_factor: float, camera_factor: float
) -> PerceptionFrame:
    """``truth`` without the vehicles and lights beyond the sensors' ranges times
    ``range_factor`` and the given factors (noise off, another detection range)."""
    nb, f = truth.neighbours, sensors.range_factor
    if compiled.enabled():
        vehicle, dist, veh, state, ldist = sensing_kernel.within_range(
            truth.vehicles, nb.vehicle, nb.distance, truth.light_state, truth.light_dist,
            sensors.lidar_range * lidar_factor * f, sensors.camera_range * camera_factor * f,
        )  # fmt: skip
        sensed_nb = replace(nb, vehicle=vehicle, distance=dist)
        return PerceptionFrame(sensed_nb, veh, truth.ego, state, ldist, truth.give_way)
    seen = (nb.vehicle >= 0) & (np.abs(nb.distance) <= sensors.lidar_range * lidar_factor * f)
    veh = np.where(seen[..., None], truth.vehicles, 0.0)
    dist = np.where(seen, nb.distance, np.where(np.arange(2) == 0, np.inf, -np.inf))
    lit = truth.light_dist <= sensors.camera_range * camera_factor * f
    state = np.where(lit, truth.light_state, NO_LIGHT).astype(np.int8)
    sensed_nb = replace(nb, vehicle=np.where(seen, nb.vehicle, -1), distance=dist)
    return PerceptionFrame(
        sensed_nb, veh, truth.ego, state, np.where(lit, truth.light_dist, np.inf), truth.give_way
    )


def _degrade_compiled(truth: PerceptionFrame, w: WeatherPreset, sensors: SensorConfig,
                      draws: tuple[np.ndarray, ...]) -> PerceptionFrame:  # fmt: skip
    """:func:`degrade` on ``draws`` (``noise_draws``) as one kernel (:mod:`.sensing_kernel`)."""
    nb, f = truth.neighbours, sensors.range_factor
    vehicle, dist, veh, ego, state, ldist = sensing_kernel.degrade(
        truth.vehicles, nb.vehicle, nb.distance, truth.ego, truth.light_state, truth.light_dist,
        *draws, sensors.lidar_range * w.lidar_range_factor * f,
        sensors.camera_range * w.camera_range_factor * f, w.rel_noise, w.light_misdetect,
        VEHICLE_NOISE_FLOOR, EGO_NOISE_FLOOR, EGO_NOISY,
    )  # fmt: skip
    sensed_nb = replace(nb, vehicle=vehicle, distance=dist)
    return PerceptionFrame(sensed_nb, veh, ego, state, ldist, truth.give_way)
