"""``python -m mixed_traffic.scenario --list``: the bundled scenarios with lanes and lengths."""

from __future__ import annotations

import argparse
import sys

from mixed_traffic.world.registry import list_scenarios, load_scenario


def scenario_table() -> list[dict[str, object]]:
    """One row per bundled scenario: name, family, split, lanes, lengths."""
    rows = []
    for name in list_scenarios():
        s = load_scenario(name)
        hd = s.hdmap
        rows.append(
            {
                "name": name,
                "family": s.family,
                "split": s.split,
                "lanes": s.lanes,
                "network_km": round(float(hd.edge_length.sum()) / 1000, 2),
                "measurement_m": round(s.measurement_length),
                "description": s.description,
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mixed_traffic.scenario", description="Bundled SUMO scenarios."
    )
    parser.add_argument("--list", action="store_true", help="list scenarios with lengths and lanes")
    parser.add_argument(
        "--build", metavar="NAME", help="build one scenario's network and print its path"
    )
    args = parser.parse_args(argv)
    if args.build:
        print(load_scenario(args.build).net_file)
        return 0
    rows = scenario_table()
    n = 2 + max(len(str(r["name"])) for r in rows)  # columns as wide as the longest names
    f = 2 + max(len(str(r["family"])) for r in rows)
    print(f"{'name':<{n}}{'family':<{f}}{'split':<7}{'lanes':>6}{'net km':>8}{'meas m':>8}  "
          "description")  # fmt: skip
    for r in rows:
        print(
            f"{r['name']:<{n}}{r['family']:<{f}}{r['split']:<7}{r['lanes']:>6}"
            f"{r['network_km']:>8}{r['measurement_m']:>8}  {r['description']}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
