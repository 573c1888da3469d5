"""What a step asks SUMO beyond the snapshot: whether the agents near a yielding junction may
go (give-way lines), which lane SUMO takes where a lane fans out, and the routes SUMO changed
(rerouters, rerouting devices)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from mixed_traffic.env.agent_table import AgentTable, Rows
from mixed_traffic.sensing.camera import GREEN, NO_LIGHT, RED, permissive
from mixed_traffic.sensing.lane_graph import lane_graph
from mixed_traffic.sensing.merges import exit_table
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot


def give_way_gates(
    hd: HDMap, backend: SumoBackend, snap: TrafficSnapshot, rows: Rows, nxt: np.ndarray,
    tls: list[str], camera_range: float,
) -> np.ndarray:  # fmt: skip
    """(A,) camera code of the give-way line ahead (``camera.give_way``) of agents within
    ``camera_range`` [m] of a junction where their lane yields, or whose signal shows a
    permissive green (g: yield to the foes) or is off (o); SUMO is asked only for those
    whether their next link is open. ``nxt`` (A,): the next route edge; ``tls``: the signal
    states."""
    lane = snap.lane[rows.r]
    out = np.full(len(lane), NO_LIGHT, dtype=np.int8)
    safe = np.maximum(lane, 0)
    yields = hd.lane_yields[safe] | permissive(lane_graph(hd), lane, nxt, tls)
    if not yields.any():  # nothing to ask SUMO
        return out
    to_end = hd.lane_length[safe] - snap.lane_pos[rows.r]
    near = (lane >= 0) & yields & (to_end <= camera_range)
    if near.any():
        idx = np.flatnonzero(near)
        out[idx] = np.where(backend.must_yield([rows.ids[i] for i in idx]), RED, GREEN)
    return out


def fan_choices(
    hd: HDMap, backend: SumoBackend, snap: TrafficSnapshot, rows: Rows, nxt: np.ndarray,
    reach: float,
) -> np.ndarray | None:  # fmt: skip
    """(A,) lane row each agent enters at the end of its lane where that lane fans out onto
    several lanes of the next edge (``HDMap.lane_fans``) and ends within ``reach`` [m]: SUMO
    picks one by its best lanes and their occupancy, not the map's first; -1 elsewhere, and
    where SUMO's next link leaves the route (next route edge ``nxt`` (A,): a lane the agent
    must still change out of). None when no agent is at such a lane (SUMO is asked only for
    those)."""
    lane = snap.lane[rows.r]
    safe = np.maximum(lane, 0)
    near = hd.lane_length[safe] - snap.lane_pos[rows.r] <= reach
    ask = np.flatnonzero((lane >= 0) & hd.lane_fans[safe] & near)
    if not len(ask):
        return None
    out = np.full(len(lane), -1, dtype=np.int64)
    vias = backend.next_vias([rows.ids[i] for i in ask])
    chosen = np.array([hd.lane_row.get(v, -1) for v in vias], dtype=np.int64)
    csafe = np.maximum(chosen, 0)
    exit_lane, _ = exit_table(hd)  # through the junction lanes to the lane it lands on
    land = np.where((chosen < 0) | (hd.lane_edge[csafe] >= 0), chosen, exit_lane[csafe])
    on_route = (land >= 0) & (hd.lane_edge[np.maximum(land, 0)] == np.asarray(nxt)[ask])
    out[ask] = np.where(on_route, chosen, -1)
    return out


def follow_sumo_routes(
    table: AgentTable, backend: SumoBackend, snap: TrafficSnapshot, rows: Rows,
    route_rows: Callable[[Sequence[str]], np.ndarray],
) -> None:  # fmt: skip
    """Re-read the routes SUMO changed (a rerouter, a rerouting device): SUMO keeps a vehicle
    on its route, so an agent whose stored route lacks its edge at SUMO's route index was
    given a new one. The table and ``snap`` get the new route (edge rows by ``route_rows``)
    and index."""
    r = rows.r
    edge, ri = snap.edge[r], snap.route_index[r]
    ok = (ri >= 0) & (ri < table.route_len[rows.slots])
    width = table.route_table.shape[1]
    stored = table.route_table[rows.slots, np.clip(ri, 0, width - 1)]
    stale = np.flatnonzero((edge >= 0) & ~(ok & (stored == edge))).tolist()
    changed = backend.refresh_routes([rows.ids[k] for k in stale]) if stale else []
    for k, (route, index) in zip(stale, changed):
        table.set_route(rows.ids[k], route_rows(route))
        snap.route_index[r[k]], snap.route_length[r[k]] = index, len(route)
