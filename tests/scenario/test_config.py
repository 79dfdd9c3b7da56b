"""Scenario loading: typed dataclasses, defaults, digest."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
from conftest import PAPER_SCENARIO, ROOT, dump_toml, scenario_table

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fleet import FleetConfig
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import SectionScenario


def test_paper_scenario_loads_into_typed_dataclasses():
    """A ring file is the closed one-lane section of its generated net, its fleet the demand."""
    sc = load_scenario(PAPER_SCENARIO)
    assert isinstance(sc, SectionScenario) and isinstance(sc.fleet, FleetConfig)
    assert (sc.name, sc.seed) == ("ring_paper", 2024)
    assert sc.network.kind == "sumo" and sc.section.closed
    assert list(sc.section.edges) == ["e0", "e1", "e2", "e3"]
    assert sc.fleet.n_vehicles == 5 and type(sc.fleet.n_vehicles) is int
    assert sc.fleet.accel_mps2 == (0.8, 1.2)
    assert sc.fleet.max_speed_mps == (50.0, 50.0)
    assert sc.speed_limits.range_mps == (12.0, 14.0)
    assert sc.simulation.step_length_s == 0.5 and sc.simulation.n_runs == 40
    assert sc.bounds.accel_mps2 == (-1.1, 0.5)
    assert sc.generator.hidden_train == (0, 5) and sc.generator.t_max == 20
    # eta 0.6 with a 0.1 m/s speed scale: a documented departure (paper: 0.3, relative error)
    assert sc.policy.eta == 0.6 and sc.policy.macro_speed_scale_mps == 0.1
    assert sc.policy.horizon == 10
    assert sc.source == str(PAPER_SCENARIO.resolve())
    assert sc.resolve(sc.network.net_file) == (ROOT / "sumo_nets" / "ring_r100_e4.net.xml")
    with pytest.raises(dataclasses.FrozenInstanceError):
        sc.seed = 1  # type: ignore[misc]


def test_omitted_tables_and_keys_take_defaults(make_scenario):
    sc = load_scenario(make_scenario(drop=("detectors", "fleet.delta", "speed_limits.step_mps")))
    assert sc.detectors.interval_s == 60.0
    assert sc.fleet.delta == 4.0
    assert sc.speed_limits.step_mps == 0.5


def test_overrides_are_applied_and_validated(make_scenario):
    path = make_scenario()
    assert load_scenario(path, {"simulation.n_runs": 3}).simulation.n_runs == 3
    with pytest.raises(UserError, match=r"fleet\.n_vehicles"):
        load_scenario(path, {"fleet.n_vehicles": 1})


def test_joint_refinement_keys_load_in_their_ranges_and_change_nothing_when_off(make_scenario):
    """policy.refine_* (stop 27, back from the ring wing): their old names and ranges; at
    their defaults the scenario's dict and digest are those of a file without them."""
    path = make_scenario()
    sc = load_scenario(path, {"policy.refine_iterations": 2, "policy.refine_lambda_rec": 0.5})
    assert (sc.policy.refine_iterations, sc.policy.refine_lambda_rec) == (2, 0.5)
    assert sc.to_dict()["policy"]["refine_iterations"] == 2
    off = {
        "policy.refine_iterations": 0,
        "policy.refine_updates": 20,
        "policy.refine_epochs": 20,
        "policy.refine_lambda_rec": 1.0,
    }
    assert load_scenario(path, off).digest() == load_scenario(path).digest()
    assert "refine_epochs" not in load_scenario(path).to_dict()["policy"]
    for key, bad, accepted in (
        ("policy.refine_iterations", 101, r"\[0, 100\]"),
        ("policy.refine_updates", 0, r"\[1, 1e\+06\]"),
        ("policy.refine_epochs", 2.5, r"\[1, 100000\]"),
        ("policy.refine_lambda_rec", -1.0, r"\[0, 1e\+06\]"),
    ):
        with pytest.raises(UserError, match=rf"^{path}: {key} = .*{accepted}$"):
            load_scenario(path, {key: bad})


def test_road_ring_and_removed_keys_name_the_change(make_scenario):
    """Stop 25 removed the ring wing: its switch and its keys are one line each, naming what
    to do; road = "section" (what every file is now) still loads."""
    path = make_scenario()
    assert load_scenario(path, {"road": "section"}).name == "ring_paper"
    with pytest.raises(UserError, match=r"road = 'ring' was removed \(stop 25\)"):
        load_scenario(path, {"road": "ring"})
    section = PAPER_SCENARIO.parent / "ring_paper_section.toml"
    with pytest.raises(UserError, match=r"replaced by generator\.eval_completions"):
        load_scenario(section, {"evaluation.completions_per_scene": 4})
    with pytest.raises(UserError, match=r"evaluation\.timespace_s was removed in stop 32"):
        load_scenario(section, {"evaluation.timespace_s": 60.0})
    # On a ring file the key still maps onto generator.eval_completions.
    assert load_scenario(path).generator.eval_completions == 4


def test_digest_is_stable_and_ignores_formatting(tmp_path):
    table = scenario_table()
    plain = tmp_path / "plain.toml"
    plain.write_text(dump_toml(table))
    # Same values, other formatting: comments, blank lines, keys in another order.
    text = "# a comment\n\n" + dump_toml(dict(reversed(list(table.items()))))
    fancy = tmp_path / "fancy.toml"
    fancy.write_text(text.replace("\n[", "\n# section\n["))
    digest = load_scenario(plain).digest()
    assert len(digest) == 64 and int(digest, 16) >= 0
    assert load_scenario(plain).digest() == digest
    assert load_scenario(fancy).digest() == digest
    # ... and in a fresh interpreter (no dependence on hash seeds or object ids).
    code = (
        "from macromicro_sumo.scenario.load import load_scenario; import sys; "
        "print(load_scenario(sys.argv[1]).digest())"
    )
    fresh = subprocess.run(
        [sys.executable, "-c", code, str(plain)], capture_output=True, text=True, check=True
    )
    assert fresh.stdout.strip() == digest


def test_digest_changes_with_any_value(make_scenario):
    base = load_scenario(make_scenario()).digest()
    assert load_scenario(make_scenario({"seed": 2025}, name="s.toml")).digest() != base
    assert load_scenario(make_scenario({"fleet.delta": 4.5}, name="d.toml")).digest() != base
    # A default written out explicitly is the same scenario.
    explicit = make_scenario({"detectors.interval_s": 60.0}, name="e.toml")
    assert load_scenario(explicit).digest() == base


def test_staging_moves_manifests_last(tmp_path):
    """A stage is done when its manifest exists: it must arrive after every other output."""
    import os

    from macromicro_sumo.files import staging_dir

    seen = []
    real = os.replace

    def spy(src, dst):
        seen.append(os.path.basename(dst))
        return real(src, dst)

    os.replace = spy
    try:
        with staging_dir(tmp_path) as stage:
            for name in ("a.csv", "manifest.json", "z.csv", "policy_manifest.json"):
                (stage / name).write_text("x")
    finally:
        os.replace = real
    assert seen[-2:] == ["manifest.json", "policy_manifest.json"] and set(seen[:2]) == {
        "a.csv",
        "z.csv",
    }


# Choices that load only with another key changed too: a ring file has other tables, and
# field data needs its files.
NEEDS_COMPANION = {("network.kind", "ring"), ("data.source", "files")}


def _choice_fields(obj: object, prefix: str = ""):
    """(dotted key, choices) of every string field with choices, nested tables included."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _choice_fields(value, f"{prefix}{f.name}.")
        elif f.metadata.get("choices") and isinstance(value, str):
            yield f"{prefix}{f.name}", f.metadata["choices"]


def test_every_named_option_loads_its_choices_and_refuses_others_in_one_line():
    """Every option with choices (deploy.safety_brake, deploy.safety_floor_on, the policy's
    and the generator's switches, the field-data units ...) on a section file: each accepted
    value loads as itself; another is a one-line error naming the file, the key and every
    accepted value."""
    path = ROOT / "scenarios" / "ring_two_lane.toml"
    fields = list(_choice_fields(load_scenario(path)))
    assert {"deploy.safety_brake", "deploy.safety_floor_on", "policy.prior"} <= dict(fields).keys()
    for key, choices in fields:
        for choice in choices:
            if (key, choice) in NEEDS_COMPANION:
                continue
            value = load_scenario(path, {key: choice})
            for part in key.split("."):
                value = getattr(value, part)
            assert value == choice, (key, choice)
        with pytest.raises(UserError) as err:
            load_scenario(path, {key: "no-such-choice"})
        msg = str(err.value)
        assert "\n" not in msg and str(path) in msg and key in msg, msg
        assert all(c in msg for c in choices), msg
