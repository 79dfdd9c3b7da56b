"""The typical vType (``data.vtypes.typical``) of a plain demand and of a spread one
(``truth.vtype_spread``: each vType a distribution of members of other lengths and minGaps),
read from real route files as the ground truth reads them (``sumo.demand.check_demand``,
``truth.vtypes.vtype_frame``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import sumo

from macromicro_sumo.data.vtypes import MEMBER_SEP, typical, typical_row
from macromicro_sumo.sumo.demand import check_demand
from macromicro_sumo.sumo.inputs import SumoInputs, read_net
from macromicro_sumo.truth.vtype_spread import SPREAD_MEMBERS, spread_routes
from macromicro_sumo.truth.vtypes import vtype_frame

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
ROUTE = '<route edges="1fi 1si 2o 2fo"/>'


def frame(route_file: Path, vehicles: dict[str, int]) -> pd.DataFrame:
    """vtypes.csv's frame of ``route_file``'s demand with ``vehicles`` per vType driven."""
    used = check_demand(SumoInputs(CROSS, (route_file,), (), None), read_net(CROSS))
    traj = pd.DataFrame(
        [{"vtype": v, "vehicle_id": f"{v}.{i}"} for v, n in vehicles.items() for i in range(n)],
        columns=["vtype", "vehicle_id"],
    )
    return vtype_frame(used, {}, traj)


def routes(folder: Path) -> Path:
    """A car (SUMO's passenger defaults: 5 m, 2.5 m) and a truck (12 m, 3 m), one vehicle
    of each."""
    path = folder / "r.rou.xml"
    path.write_text(
        '<routes>\n<vType id="car"/>\n<vType id="truck" vClass="truck" length="12" minGap="3"/>\n'
        f'<vehicle id="c" type="car" depart="0">{ROUTE}</vehicle>\n'
        f'<vehicle id="t" type="truck" depart="1">{ROUTE}</vehicle>\n</routes>\n'
    )
    return path


def test_plain_demand_keeps_the_vtype_with_most_vehicles(tmp_path: Path) -> None:
    """Without members the typical vType is the one with the most vehicles, as before."""
    vt = frame(routes(tmp_path), {"car": 3, "truck": 5})
    assert typical(vt, "vtype") == "truck"
    assert typical(vt, "length_m") == 12.0
    vt = frame(routes(tmp_path), {"car": 6, "truck": 5})
    assert typical(vt, "vtype") == "car" and typical(vt, "length_m") == 5.0


def test_spread_demand_takes_the_member_nearest_the_largest_distributions_mean(
    tmp_path: Path,
) -> None:
    """A spread demand: the distribution with the most vehicles (the cars, 2 per member:
    40, though one truck member alone has 30) and of its members the one nearest its mean
    length and minGap (vehicle-weighted), not its member with the most vehicles (given 10,
    the one farthest from the vType's 5 m and 2.5 m)."""
    spread = spread_routes(routes(tmp_path), tmp_path / "s.rou.xml", 7)
    cars = [f"car{MEMBER_SEP}{i:02d}" for i in range(SPREAD_MEMBERS)]
    shape = frame(spread, {}).set_index("vtype").loc[cars, ["length_m", "min_gap_m"]]
    far = str(((shape - [5.0, 2.5]) ** 2).sum(axis=1).idxmax())
    counts = {c: 2 for c in cars} | {far: 10, f"truck{MEMBER_SEP}00": 30}
    vt = frame(spread, counts)
    assert str(vt["vtype"].iloc[int(np.argmax(vt["vehicles"]))]).startswith("truck")
    pick = str(typical(vt, "vtype"))
    assert pick in cars and pick != far
    w = vt.set_index("vtype").loc[cars, "vehicles"].to_numpy(dtype=float)
    mean = (shape.to_numpy() * w[:, None]).sum(axis=0) / w.sum()
    got = np.array([typical(vt, "length_m"), typical(vt, "min_gap_m")], dtype=float)
    dist = ((shape.to_numpy() - mean) ** 2).sum(axis=1)
    assert np.isclose(((got - mean) ** 2).sum(), dist.min())
    # Nearer the distribution's own mean (5 m, 2.5 m) than the member with most vehicles.
    assert np.abs(got - [5.0, 2.5]).sum() < np.abs(shape.loc[far].to_numpy() - [5.0, 2.5]).sum()
    assert typical_row(vt) == int(np.flatnonzero(vt["vtype"] == pick)[0])
