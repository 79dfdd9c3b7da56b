"""vtypes.csv records each vType's decel as SUMO drives it (the value its routes file sets,
else SUMO's default for its vClass): what a driven vehicle's safe speed, the deployment's
safety layer, brakes at. Real SUMO: one lane, vans that set decel, cars that do not."""

from __future__ import annotations

import pandas as pd
from conftest import dump_toml, line_net

from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

SUMO_PASSENGER_DECEL_MPS2 = 4.5  # sumo.dlr.de/docs/Vehicle_Type_Parameter_Defaults.html


def test_vtypes_csv_records_sumos_decel_of_each_vtype(tmp_path) -> None:
    net = line_net(tmp_path, (800.0,), 1, 20.0)
    routes = tmp_path / "mix.rou.xml"
    routes.write_text(
        "<routes>\n"
        '    <vType id="van" length="6" decel="3.5" maxSpeed="15"/>\n'
        '    <vType id="car" length="5"/>\n'
        '    <flow id="v" type="van" begin="0" end="60" period="6"><route edges="A"/></flow>\n'
        '    <flow id="c" type="car" begin="3" end="60" period="6"><route edges="A"/></flow>\n'
        "</routes>\n"
    )
    table = {
        "name": "mix",
        "network": {"kind": "sumo", "net_file": str(net), "route_files": [str(routes)]},
        "section": {"edges": ["A"]},
        "instrumented": {"penetration": 0.5},
        "simulation": {"warmup_s": 10.0, "duration_s": 50.0, "n_runs": 1},
        "detectors": {"interval_s": 25.0},
    }
    path = tmp_path / "mix.toml"
    path.write_text(dump_toml(table))
    sc = load_scenario(path)
    gt = simulate_section(sc, tmp_path / "gt", progress=False)
    vt = pd.read_csv(gt / "vtypes.csv")
    decel = dict(zip(vt["vtype"], vt["decel_mps2"], strict=True))
    assert decel == {"van": 3.5, "car": SUMO_PASSENGER_DECEL_MPS2}
    assert (vt["vehicles"] > 0).all()
    truth = load_section_truth(gt, sc)
    assert truth.vtypes.set_index("vtype")["decel_mps2"].to_dict() == decel
