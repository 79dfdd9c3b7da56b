"""The paper's ring file read as a section scenario: how a ring file loads.

Issue 16 wants one road model: a ring file (``[network] radius_m``, ``n_edges``, ``net_file``,
``routes_file``, the IDM fleet) is the closed one-lane section of its generated ring network
with the fleet as its demand. ``ring_to_section`` rewrites a ring file's raw table into the
section table that ``scenarios/ring_paper_section.toml`` spells out, and the section wing
runs it. Keys keep their names where both wings have them; a ring key whose value the
section cannot express is a one-line ``UserError`` naming the key and its replacement.
A section key that the file gives inside the ring's tables (``simulation.warmup_s``,
``generator.dispersion_error``) overrides what the mapping fills in; the section's own
tables (``[section]``, ``[instrumented]``, ``[data]``) are the mapping's, not the file's.

Since stop 25 this mapping is how every ring file loads (the ring wing is gone); the ring's
generator defaults where they differ from the section's are ``RING_GENERATOR_DEFAULTS``.
"""

from __future__ import annotations

import copy
import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from macromicro_sumo.errors import UserError

# The ring's generator defaults where the section's differ (the ring wing's, until stop 25):
# a ring file that leaves them out meant these.
RING_GENERATOR_DEFAULTS: dict[str, Any] = {
    "epochs": 60,
    "batch_size": 256,
    "patience": 10,
    "snapshot_every_s": 5.0,
    "spacing_dispersion": "paper",
    "bounds_source": "interval",
}

# The tables and top-level keys of a ring file; the mapped table
# may add section keys to them (their own validation then applies).
RING_TOP = (
    "name",
    "seed",
    "network",
    "fleet",
    "speed_limits",
    "initial",
    "simulation",
    "detectors",
    "bounds",
    "generator",
    "policy",
    "evaluation",
    "deploy",
)
RING_NETWORK = ("kind", "radius_m", "n_edges", "net_file", "routes_file")
# The keys of a ring file that a section file does not have, with their types (a batch's
# ``[sweep]`` of a ring file accepts them beside the section keys of its tables).
RING_FILE_KEYS: dict[str, Any] = {
    "network.radius_m": float,
    "network.n_edges": int,
    "network.net_file": str,
    "network.routes_file": str,
    "bounds.speed_mps": tuple[float, float],
    "bounds.spacing_m": tuple[float, float],
    "generator.lambda_rec": float,
    "generator.psi_source": str,
    "detectors.e1_position": float,
    "evaluation.completions_per_scene": int,
}
# Required by the ring and defaulted differently (or not at all) by the section.
RING_REQUIRED = (
    "name",
    "network.radius_m",
    "network.net_file",
    "fleet",
    "speed_limits",
    "initial",
    "simulation.duration_s",
    "simulation.n_runs",
    "bounds.accel_mps2",
)
# The ring truth's loops sit at mid-edge; the section reads them from the detector file
# beside the net (``detector_file``), which places them there.
E1_POSITION = 0.5
RADIUS_TOLERANCE_M = 1e-3  # as the ring truth's check of the net against 2 pi R


def detector_file(net_file: str) -> str:
    """The ring's detectors as a user's own, beside ``net_file`` (as written in the file):
    ``ring_r100_e4.net.xml`` -> ``ring_r100_e4.det.add.xml``."""
    stem = net_file.removesuffix(".xml").removesuffix(".net")
    return f"{stem}.det.add.xml"


def _table(table: dict[str, Any], name: str, file: str) -> dict[str, Any]:
    value = table.setdefault(name, {})
    if not isinstance(value, dict):
        raise UserError(f"{file}: [{name}] must be a table")
    return value


def _require(table: dict[str, Any], file: str) -> None:
    """The keys a ring file must give (``RING_REQUIRED``), as the ring's loader asks them."""
    for dotted in RING_REQUIRED:
        node: Any = table
        for part in dotted.split("."):
            if not isinstance(node, dict) or part not in node:
                table_name = "." not in dotted and dotted != "name"
                what = f"table [{dotted}]" if table_name else f"key {dotted!r}"
                raise UserError(f"{file}: missing required {what}")
            node = node[part]


def _refuse(key: str, value: Any, accepted: Any, why: str, file: str) -> None:
    """A ring key whose value has no section meaning: one line naming its replacement."""
    if value != accepted:
        raise UserError(
            f"{file}: {key} = {value!r} has no section meaning with road = 'section' ({why}); "
            f"accepted {accepted!r} or remove the key"
        )


def _pair(value: Any, key: str, hi: float, file: str) -> None:
    """A [low, high] pair of numbers in [0, hi], low <= high (one-line error otherwise)."""
    ok = isinstance(value, list) and len(value) == 2
    ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    if not ok or not 0 <= value[0] <= hi or not 0 <= value[1] <= hi:
        raise UserError(f"{file}: {key} = {value!r} must be a pair [low, high] in [0, {hi:g}]")
    if value[0] > value[1]:
        raise UserError(
            f"{file}: {key} = {value!r} is reversed; accepted [low, high] with low <= high, "
            f"both in [0, {hi:g}]"
        )


def ring_length_m(net: Path, edges: list[str], file: str) -> float:
    """The lane length of ``edges`` in the SUMO net ``net`` [m] (one-line error when one of
    them is missing)."""
    try:
        root = ET.parse(net).getroot()
    except (OSError, ET.ParseError) as exc:
        raise UserError(
            f"{file}: network.net_file = {net} is not a readable SUMO network ({exc})"
        ) from None
    lanes = {
        e.get("id"): e.find("lane")
        for e in root.iter("edge")
        if e.get("function") != "internal" and e.find("lane") is not None
    }
    missing = [e for e in edges if e not in lanes]
    if missing:
        raise UserError(
            f"{file}: network.n_edges = {len(edges)} names edge {missing[0]}, which {net} "
            f"lacks; accepted: the net's ring edges e0..e{len(lanes) - 1}"
        )
    return sum(float(lanes[e].get("length", "nan")) for e in edges)


def _network(table: dict[str, Any], folder: Path, file: str) -> tuple[dict, dict]:
    """(the section's [network], its [section]) from the ring's [network]."""
    net = table["network"]
    unknown = sorted(set(net) - set(RING_NETWORK))
    if unknown:
        raise UserError(
            f"{file}: unknown key [network] {unknown[0]!r}; accepted keys: "
            f"{', '.join(sorted(RING_NETWORK))}"
        )
    _refuse("network.kind", net.get("kind", "ring"), "ring", "a ring file", file)
    net_file = net["net_file"]
    n_edges = net.get("n_edges", 4)
    if not isinstance(net_file, str):
        raise UserError(f"{file}: network.net_file = {net_file!r} must be a string")
    if isinstance(n_edges, bool) or not isinstance(n_edges, int) or not 1 <= n_edges <= 64:
        raise UserError(f"{file}: network.n_edges = {n_edges!r} is out of range; accepted: [1, 64]")
    radius = net["radius_m"]
    if isinstance(radius, bool) or not isinstance(radius, int | float) or radius <= 0:
        raise UserError(f"{file}: network.radius_m = {radius!r} must be a number in (0, 1e5]")
    edges = [f"e{k}" for k in range(n_edges)]
    net_path = folder / net_file
    if not net_path.is_file():
        raise UserError(f"{file}: network.net_file = {net_path} does not exist")
    # The section's length is the net's: radius_m only names it, so it must agree.
    length = ring_length_m(net_path, edges, file)
    if abs(length - 2 * math.pi * radius) > RADIUS_TOLERANCE_M:
        raise UserError(
            f"{file}: network.radius_m = {radius:g} (2 pi R = {2 * math.pi * radius:.4f} m) "
            f"does not match {net_path}'s ring of {length:.4f} m; the section's length is the "
            f"net's: accepted radius_m = {length / (2 * math.pi):.4f} or another net_file"
        )
    dets = detector_file(net_file)
    if not (folder / dets).is_file():
        raise UserError(
            f"{file}: network.net_file = {net_file!r} has no ring detector file {dets} beside "
            "it (an E1 loop at mid-edge and an E2 over every edge, as "
            "sumo_nets/ring_r100_e4.det.add.xml); accepted: a net that has one"
        )
    # routes_file (one-lap routes and rerouters) is dropped: the fleet writes its own loop
    # routes (sumo/fleet.py), and a section fleet refuses route files.
    network = {"kind": "sumo", "net_file": net_file, "additional_files": [dets]}
    return network, {"edges": edges, "closed": True}


def ring_to_section(table: dict[str, Any], folder: Path, file: str) -> dict[str, Any]:
    """The section table (raw, for ``build_section_scenario``) equivalent to the ring file's
    raw ``table`` (without ``road`` and ``[sweep]``); ``folder``: the file's folder, against
    which its paths resolve."""
    table = copy.deepcopy(table)
    unknown = sorted(set(table) - set(RING_TOP))
    if unknown:
        raise UserError(
            f"{file}: unknown key {unknown[0]!r} in a ring file; accepted keys: "
            f"{', '.join(sorted(RING_TOP))}"
        )
    _require(table, file)
    for name in RING_TOP[2:]:
        _table(table, name, file)
    network, section = _network(table, folder, file)
    table["network"] = network
    table["section"] = section

    gen = table["generator"]
    for key, value in RING_GENERATOR_DEFAULTS.items():
        gen.setdefault(key, value)
    _refuse(
        "generator.lambda_rec",
        gen.pop("lambda_rec", 0.0),
        0.0,
        "the section generator has no reconstruction term",
        file,
    )
    _refuse(
        "generator.psi_source",
        gen.pop("psi_source", "detectors"),
        "detectors",
        "psi is the detectors' on a section",
        file,
    )
    if gen["bounds_source"] == "fixed":
        _refuse(
            "generator.bounds_source",
            "fixed",
            "extended",
            "a section measures psi's bounds per detector interval, bounds.speed_mps and "
            "spacing_m are the ring's fixed ones",
            file,
        )
    # The paper's fixed bounds were read only by bounds_source = "fixed" (refused above): a
    # ring file keeps them for reference, checked as pairs, and the section measures its own.
    bounds = table["bounds"]
    for key, hi in (("speed_mps", 100.0), ("spacing_m", 1e6)):
        _pair(bounds.pop(key, [0.0, 0.0]), f"bounds.{key}", hi, file)
    # The ring's safety gap is its fleet's smallest jam distance (env/ring.py).
    min_gap = table["fleet"].get("min_gap_m")
    if isinstance(min_gap, list) and min_gap:
        bounds.setdefault("min_gap_m", min_gap[0])

    # The ring knows N: K is given, and every snapshot hides K random vehicles of the fully
    # recorded fleet. penetration only decides k_estimate.csv and who the deployment drives.
    gen.setdefault("k_source", "truth")
    table["instrumented"] = {"hidden": "snapshot", "penetration": 0.5}
    # The ring's completions per held-out scene: the section draws them in the generator's
    # held-out metrics (its evaluation draws one; docs/design.md, "Ring as a section").
    evaluation = table["evaluation"]
    gen.setdefault("eval_completions", evaluation.pop("completions_per_scene", 1))
    if gen["spacing_dispersion"] == "measured":
        # Around the loop the scene's mean spacing is exact where psi's is an estimate (E2),
        # and the squared error makes the completions' mean spacing variance meet psi's
        # (docs/design.md, "Ring as a section: status", items 2 and 3).
        gen.setdefault("dispersion_center", "scene")
        gen.setdefault("dispersion_error", "squared")
        # ... and the ring's A with each gap's dispersion budget (K = 1's spread, item 3)
        gen.setdefault("spacing_set", "touched")
        gen.setdefault("dispersion_feature", True)
        # ... and what makes K = 2..4 hold across training seeds: the scenes' summed
        # spacing variance per K against psi's, the ring generator's two hidden layers, and
        # an average that lets go of the initial weights, with no stop on its early plateau
        # (docs/design.md, "Ring as a section: status", item 3)
        gen.setdefault("dispersion_pool", 1.0)
        gen.setdefault("hidden_layers", 2)
        gen.setdefault("ema_warmup", True)
        gen.setdefault("min_epochs", 150)

    table["simulation"].setdefault("warmup_s", 0.0)  # the ring records from the insertion on
    detectors = table["detectors"]
    _refuse(
        "detectors.e1_position",
        detectors.pop("e1_position", E1_POSITION),
        E1_POSITION,
        f"the loops are those of the detector file {network['additional_files'][0]}",
        file,
    )
    detectors.setdefault("use_user", True)
    return table
