"""Build the exact ring network checked in under sumo_nets/.

python scripts/build_ring_net.py --radius 100 --edges 4 --name ring_r100_e4
python scripts/build_ring_net.py --radius 100 --edges 4 --lanes 2 --out sumo_nets/ring2_r100 --name ring2_r100_e4
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from macromicro_sumo.road.ring import build_ring
from macromicro_sumo.road.section import read_section


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--radius", type=float, default=100.0, help="ring radius R [m]")
    ap.add_argument("--edges", type=int, default=4, help="number of edges (speed-limit pieces)")
    ap.add_argument("--lanes", type=int, default=1, help="lanes per edge")
    ap.add_argument("--name", default=None, help="file stem (default ring_r<R>_e<edges>)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "sumo_nets")
    args = ap.parse_args(argv)
    name = args.name or f"ring_r{args.radius:g}_e{args.edges}"
    net, add = build_ring(args.radius, args.edges, args.out, name, lanes=args.lanes)
    sec = read_section(net, [f"e{k}" for k in range(args.edges)], closed=True)
    err = sec.length_m - 2 * math.pi * args.radius
    print(
        f"{net}: {args.edges} edges, {args.lanes} lane(s), length {sec.length_m:.6f} m "
        f"(2 pi R error {err * 1e3:+.3f} mm)"
    )
    print(f"{add}: routes and rerouters")
    return 0 if abs(err) < 1e-3 else 1


if __name__ == "__main__":
    raise SystemExit(main())
