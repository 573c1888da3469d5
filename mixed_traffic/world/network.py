"""Bundled networks: built from plain SUMO XML sources with netconvert, cached by content."""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

import numpy as np

from mixed_traffic.paths import cache_dir
from mixed_traffic.world.backend import binary

SPLIT_ARGS = ("--geometry.max-segment-length", "500", "--geometry.split")
"""netconvert options that cut every edge into pieces of at most 500 m. SUMO's sublane model,
which the env runs, scans the vehicles of a lane, so a step costs about n^2 in the vehicles on
one edge: 2,000 vehicles on one 20 km edge took 154 ms per step, on 500 m edges 15 ms
(docs/results.md). Real roads are cut at every junction and ramp."""


def build_network(folder: Path) -> Path:
    """Build (or reuse the cached) .net.xml from the plain XML sources in ``folder``."""
    sources = {
        kind: sorted(folder.glob(f"*.{kind}.xml")) for kind in ("nod", "edg", "con", "tll", "typ")
    }
    if not sources["nod"] or not sources["edg"]:
        raise ValueError(f"scenario folder {folder} needs at least one .nod.xml and one .edg.xml")
    h = hashlib.sha256()
    for path in (p for paths in sources.values() for p in paths):
        h.update(path.name.encode() + path.read_bytes())
    h.update(
        (folder / "netconvert.args").read_bytes() if (folder / "netconvert.args").exists() else b""
    )
    out = cache_dir("nets") / f"{folder.parent.name}-{folder.name}-{h.hexdigest()[:16]}.net.xml"
    if out.exists():
        return out
    flags = {"nod": "--node-files", "edg": "--edge-files", "con": "--connection-files",
             "tll": "--tllogic-files", "typ": "--type-files"}  # fmt: skip
    cmd = [binary("netconvert")]
    for kind, paths in sources.items():
        if paths:
            cmd += [flags[kind], ",".join(str(p) for p in paths)]
    extra = (
        (folder / "netconvert.args").read_text().split()
        if (folder / "netconvert.args").exists()
        else []
    )
    tmp = out.with_suffix(f".tmp{np.random.randint(1 << 30)}.xml")
    cmd += ["--output-file", str(tmp), "--no-warnings", *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0 or not tmp.exists():
        tmp.unlink(missing_ok=True)
        raise ValueError(
            f"netconvert failed on {folder}: {proc.stderr.strip() or proc.stdout.strip()}"
        )
    tmp.replace(out)
    return out
