"""The traffic figures of a sweep report: the fundamental diagram (flow against density per lane)
and space-time diagrams (vehicle trajectories coloured by speed).

The fundamental diagram takes density per lane from Edie's flow and space-mean speed of each
episode (k = q / v, the same region of space and time), so it needs no lane count. The empirical
band: capacity 1,800-2,300 veh/h/lane at 18-35 veh/km/lane, jam density 120-160 veh/km/lane
(HCM 2016; Treiber & Kesting 2013).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.patches import Rectangle

from analysis.figures import new_figure, save_figure
from analysis.results import ok_rows
from analysis.style import REFERENCE_COLOR, order_policies, policy_palette
from mixed_traffic.schema import TRACE_DIR

CAPACITY_BAND = ((18.0, 35.0), (1800.0, 2300.0))
"""Empirical capacity: (density range [veh/km/lane], flow range [veh/h/lane])."""
JAM_BAND = (120.0, 160.0)
"""Empirical jam density [veh/km/lane]."""


def fd_points(df: pd.DataFrame) -> pd.DataFrame:
    """Columns ``policy``, ``penetration``, ``k`` [veh/km/lane], ``q`` [veh/h/lane] of the ok
    episodes that measured a flow."""
    ok = ok_rows(df)
    ok = ok[ok["flow"].notna() & (ok["mean_speed"] > 0)]
    return pd.DataFrame({
        "policy": ok["policy"], "penetration": ok["penetration"],
        "k": ok["flow"] / (3.6 * ok["mean_speed"]), "q": ok["flow"],
    })  # fmt: skip


def plot_fundamental_diagram(sweep: pd.DataFrame, humans: pd.DataFrame, path: Path) -> Path | None:
    """All-human traffic (``humans``: extra all-human cells, plus the sweep's 0 % cells) against
    the sweep's cells with 100 % of each AV policy; None without any flow."""
    pts = fd_points(pd.concat([sweep, humans], ignore_index=True))
    if pts.empty:
        return None
    fig, (ax,) = new_figure(6.4, 4.2)
    (k0, k1), (q0, q1) = CAPACITY_BAND
    ax.add_patch(Rectangle((k0, q0), k1 - k0, q1 - q0, color="0.85", zorder=0,
                           label="empirical capacity"))  # fmt: skip
    ax.axvspan(*JAM_BAND, color="0.92", zorder=0, label="empirical jam density")
    human = pts[pts["penetration"] == 0].sort_values("k")
    ax.plot(human["k"], human["q"], "o-", color=REFERENCE_COLOR, label="all human", ms=4)
    full = pts[(pts["penetration"] == 1.0) & (pts["policy"] != "idm")]
    palette = policy_palette(full["policy"].unique())
    for policy in order_policies(full["policy"].unique()):
        p = full[full["policy"] == policy]
        ax.scatter(p["k"], p["q"], color=palette[policy], label=f"100 % {policy}", s=22, zorder=3)
    ax.set_xlabel("density (veh/km/lane)")
    ax.set_ylabel("flow (veh/h/lane)")
    ax.set_xlim(0, max(170.0, float(pts["k"].max()) * 1.05))
    ax.set_ylim(0, max(2500.0, float(pts["q"].max()) * 1.1))
    ax.legend(fontsize=7, loc="upper right")
    return save_figure(fig, path)


def plot_space_time(traces: list[Path], path: Path) -> Path | None:
    """One panel per trace file: every vehicle's position along the measurement segment over
    time, coloured by its speed; None without traces."""
    if not traces:
        return None
    fig, axes = new_figure(6.4, 2.6 * len(traces), nrows=len(traces))
    vmax = max(float(np.load(p)["v"].max(initial=1.0)) for p in traces)
    for ax, trace in zip(axes, traces):
        data = np.load(trace)
        art = ax.scatter(data["t"], data["s"], c=data["v"], s=0.3, cmap="RdYlGn", vmin=0.0,
                         vmax=vmax, rasterized=True)  # fmt: skip
        ax.set_title(str(data["title"]), fontsize=9)
        ax.set_ylabel("position (m)")
        fig.colorbar(art, ax=ax, label="speed (m/s)")
    axes[-1].set_xlabel("time (s)")
    return save_figure(fig, path)


def trace_files(results_dir: Path) -> list[Path]:
    """The space-time traces of a results folder: the all-human reference first, then by name."""
    files = (Path(results_dir) / TRACE_DIR).glob("*.npz")
    return sorted(files, key=lambda p: (not p.name.startswith("idm-"), p.name))
