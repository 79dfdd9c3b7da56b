"""The prior's choice made once per run (``policy.chosen_prior``): the pipeline's
``choose_prior`` stage writes ``policy/prior_choice.json``, the policy and its two ablations
read it instead of each deploying the candidates again, and train on the prior a stage that
chooses for itself trains on, to the bit; a choice file of other settings or of another
ground truth is not reused (real SUMO: a one-lane road of SUMO IDM cars with a speed drop,
``policy.prior = "auto"``; a few seconds of SUMO per deployment)."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import netconvert
from section_files import routes_file, section_scenario, vtype

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.files import write_json
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.pipeline.build import (
    SECTION,
    pipeline_stages,
    run_stages,
    standard_stages,
)
from macromicro_sumo.pipeline.refinement import refine, refine_prior
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.policy.chosen_prior import CHOICE_FILE, PAIRS_FILE, read_choice
from macromicro_sumo.policy.prior import PRIOR_KEYS
from macromicro_sumo.policy.prior_choice import PriorDeploy
from macromicro_sumo.policy.relax_choice import RELAX_CANDIDATES_S
from macromicro_sumo.policy.stage import run_train_policy, stage_prior
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

OBJECTIVES = {"mix": "", "micro_only": "_micro_only", "macro_only": "_macro_only"}


@pytest.fixture(scope="module")
def auto_run(tmp_path_factory: pytest.TempPathFactory):
    """The pipeline's stages up to the three policies on a 1.4 km one-lane road (its limit
    30 then 15 m/s, SUMO IDM cars every 3 s; three runs of 60 s after a 60 s warm-up), prior
    "auto", one PPO update; every deployment of a prior alone counted (in this process:
    the counting scorer cannot go to a worker, so the stages run one after the other)."""
    folder = tmp_path_factory.mktemp("prior_once")
    net = netconvert(
        folder,
        '<node id="a" x="0" y="0"/>\n<node id="b" x="800" y="0"/>\n<node id="c" x="1400" y="0"/>',
        '<edge id="A" from="a" to="b" numLanes="1" speed="30"/>\n'
        '<edge id="B" from="b" to="c" numLanes="1" speed="15"/>',
    )
    car = vtype("car", carFollowModel="IDM", length=5.0, minGap=2.0, accel=1.5, decel=2.5)
    routes = routes_file(
        folder / "r.rou.xml",
        vtypes=[car],
        routes=['<route id="r" edges="A B"/>'],
        flows=['<flow id="f" type="car" route="r" begin="0" end="3600" period="3"/>'],
    )
    path = section_scenario(
        folder / "idm_road.toml",
        net,
        routes,
        ["A", "B"],
        seed=3,
        penetration=0.5,
        simulation={"warmup_s": 60.0, "duration_s": 60.0, "n_runs": 3},
        detectors={"interval_s": 30.0, "auto_spacing_m": 400.0},
        generator={"epochs": 2, "snapshot_every_s": 10.0},
        policy={
            "prior": "auto",
            "observation": "lookahead",
            "updates": 1,
            "episodes_per_update": 4,
            "horizon": 4,
        },
        deploy={"methods": ["policy"]},
    )
    sc = load_scenario(path)
    deployed: list[str] = []

    def score(one, data, agent):
        deployed.append(agent.prior)
        return SECTION.score_prior(one, data, agent)

    road = dataclasses.replace(SECTION, score_prior=score)
    out = folder / "run"
    stages = [s for s in pipeline_stages(sc, road, out, progress=False) if s.name != "evaluate"]
    stages = [s for s in stages if s.name != "deploy"]
    manifest = run_stages(sc, stages, out, "", progress=False, jobs=2)
    return sc, out, deployed, manifest, score


def _policy_manifest(out: Path, objective: str) -> dict:
    return json.loads((out / "policy" / f"policy_manifest{OBJECTIVES[objective]}.json").read_text())


def test_the_three_policies_read_one_choice(auto_run):
    """One choice for the three learned methods: the candidates were deployed once each
    (krauss once per relaxation candidate where it chose one), by the choice stage, and
    every policy manifest records the choice file's prior, made by no policy stage."""
    sc, out, deployed, manifest, _ = auto_run
    assert list(manifest["timings_s"])[:3] == ["simulate", "train_generator", "choose_prior"]
    choice = json.loads((out / "policy" / CHOICE_FILE).read_text())
    family, record = choice["family"], choice["prior"]
    relax = record["choice"]["candidates"]["krauss"]["relax_choice_s"]
    krauss = len(RELAX_CANDIDATES_S) if relax is not None else 1
    assert sorted(deployed) == sorted(["krauss"] * krauss + ["idm", "gipps"])
    assert record["choice"]["chosen"] == family and record["kind"] == family
    for objective in OBJECTIVES:
        m = _policy_manifest(out, objective)
        assert m["prior"] == record, objective
        assert m["prior_choice"]["made_by_this_stage"] is False, objective
        ckpt = out / "policy" / f"policy{OBJECTIVES[objective]}.pt"
        assert torch.load(ckpt, weights_only=True)["prior"] == family


def test_a_stage_that_chooses_for_itself_trains_the_same_policy(auto_run, tmp_path):
    """`train-policy` alone into a folder with no choice file chooses for itself (as every
    policy stage did before the choice stage) and writes the file: the same family and
    parameters as the pipeline's choice stage, and the same checkpoint byte for byte as
    the pipeline's policy stage that read the file."""
    sc, out, deployed, _, score = auto_run
    before = len(deployed)
    alone = tmp_path / "policy"
    gt, gen = out / "ground_truth", out / "generator" / "generator.pt"
    m = run_train_policy(
        sc, gt, gen, alone, progress=False, fit_prior=SECTION.fit_prior, score_prior=score
    )
    assert m["prior_choice"]["made_by_this_stage"] is True and len(deployed) > before
    mine = json.loads((alone / CHOICE_FILE).read_text())
    theirs = json.loads((out / "policy" / CHOICE_FILE).read_text())
    assert (mine["family"], mine["params"]) == (theirs["family"], theirs["params"])
    with np.load(alone / PAIRS_FILE) as a, np.load(out / "policy" / PAIRS_FILE) as b:
        assert np.array_equal(a["obs"], b["obs"]) and np.array_equal(a["acc"], b["acc"])
    assert (alone / "policy.pt").read_bytes() == (out / "policy" / "policy.pt").read_bytes()
    # Run again into the same folder: the file is read, nothing deployed.
    count = len(deployed)
    m = run_train_policy(
        sc, gt, gen, alone, progress=False, fit_prior=SECTION.fit_prior, score_prior=score
    )
    assert m["prior_choice"]["made_by_this_stage"] is False and len(deployed) == count


def test_a_stale_choice_file_is_said_in_one_line_and_made_again(auto_run, tmp_path, capsys):
    """A choice file of other settings the choice reads ([deploy]'s safety layer), of
    another ground truth, or whose pairs changed is not read (one line each says why); one
    of other PPO settings is. A stage finding it stale chooses again (here with a table of
    figures for the deployments: the bookkeeping) and writes the file anew."""
    sc, out, _, _, _ = auto_run
    gt, pol = out / "ground_truth", tmp_path / "policy"
    shutil.copytree(out / "policy", pol)
    path = pol / CHOICE_FILE
    assert read_choice(path, sc, gt) is not None
    eta = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, eta=0.9, updates=7))
    assert read_choice(path, eta, gt) is not None
    assert capsys.readouterr().out == ""
    brake = dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, safety_brake="matched"))
    assert read_choice(path, brake, gt) is None
    said = capsys.readouterr().out
    assert said.count("\n") == 1 and "deploy.safety_brake changed" in said and str(path) in said
    # policy.driver_follow is not read by the choice, but a Krauss choice made before the
    # drivers' taus were kept (no "levels_s") cannot give them: made again for it alone.
    follow = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, driver_follow="drawn"))
    kept = path.read_text()
    old = json.loads(kept)
    taus = {"drivers": 3, "levels_s": None}
    path.write_text(json.dumps({**old, "family": "krauss", "prior": {"driver_taus": taus}}))
    assert read_choice(path, follow, gt) is not None
    path.write_text(json.dumps({**old, "family": "krauss", "prior": {}}))
    assert read_choice(path, sc, gt) is not None
    assert capsys.readouterr().out == ""
    assert read_choice(path, follow, gt) is None
    said = capsys.readouterr().out
    assert said.count("\n") == 1 and "drivers' taus" in said
    path.write_text(kept)
    other_gt = tmp_path / "gt"
    shutil.copytree(gt, other_gt)
    manifest = json.loads((other_gt / "manifest.json").read_text())
    write_json({**manifest, "seed": manifest["seed"] + 1}, other_gt / "manifest.json")
    assert read_choice(path, sc, other_gt) is None
    said = capsys.readouterr().out
    assert said.count("\n") == 1 and "another ground truth" in said
    np.savez(pol / PAIRS_FILE, obs=np.zeros((1, 2)), acc=np.zeros(1))
    assert read_choice(path, sc, gt) is None
    assert f"{PAIRS_FILE}, are missing or changed" in capsys.readouterr().out
    path.write_text(json.dumps({**json.loads(path.read_text()), "outputs": []}))
    assert read_choice(path, sc, gt) is None
    said = capsys.readouterr().out
    assert said.count("\n") == 1 and "not a prior choice of this version" in said
    # The stage chooses again and writes the file: the deployments' figures a table.
    figures = {"krauss": 0.9, "idm": 0.3, "gipps": 0.6}
    deployed: list[str] = []

    def score(one, data, agent):
        deployed.append(agent.prior)
        return {"speed_rmse_mps": figures[agent.prior], "collisions": 0}

    truth = load_section_truth(gt, sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    deploy = PriorDeploy(score, gt)
    trained, (_, extra, _) = stage_prior(brake, truth, gt, pol, splits, SECTION.fit_prior, deploy)
    assert "choosing the prior again" in capsys.readouterr().out
    assert trained.policy.prior == "idm" and extra["prior_choice"]["made_by_this_stage"]
    assert {"idm", "gipps", "krauss"} <= set(deployed)
    assert read_choice(path, brake, gt)["family"] == "idm"


def test_the_refinement_reads_the_choice_and_trains_on_the_same_prior(auto_run, tmp_path, capsys):
    """The joint refinement takes the single pass's prior from its policy folder's choice
    file and pairs (no fit: a Krauss fit alone is half a minute); where the file is missing
    or stale (one line says so) it fits the checkpoint's family again, to the same
    parameters and pairs. Before, it fitted every time (``fit_prior`` called once)."""
    sc, out, _, _, _ = auto_run
    gt, pol = out / "ground_truth", tmp_path / "policy"
    shutil.copytree(out / "policy", pol)
    fits: list[str] = []

    def fit(one, truth, runs):
        fits.append(one.policy.prior)
        return SECTION.fit_prior(one, truth, runs)

    refined = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, refine_iterations=0))
    m = refine(refined, gt, out / "generator" / "generator.pt", pol / "policy.pt", tmp_path / "r",
               progress=False, fit_prior=fit)  # fmt: skip
    choice = json.loads((pol / CHOICE_FILE).read_text())
    assert fits == [] and m["prior_choice"]["made_by_this_stage"] is False
    assert m["prior"] == choice["prior"]
    truth = load_section_truth(gt, sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    agent = load_policy(pol / "policy.pt", sc)
    read = refine_prior(sc, truth, gt, pol / "policy.pt", agent, splits, fit)
    (pol / CHOICE_FILE).unlink()
    fitted = refine_prior(sc, truth, gt, pol / "policy.pt", agent, splits, fit)
    assert fits == [choice["family"]] and capsys.readouterr().out == ""
    brake = dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, safety_brake="matched"))
    shutil.copy(out / "policy" / CHOICE_FILE, pol / CHOICE_FILE)
    refine_prior(brake, truth, gt, pol / "policy.pt", agent, splits, fit)
    said = capsys.readouterr().out
    assert said.count("\n") == 1 and "fitting the policy's prior again" in said
    assert len(fits) == 2
    for got in (read, fitted):
        assert got[0].policy.prior == agent.prior == choice["family"]
    keys = PRIOR_KEYS[agent.prior]
    assert [read[1][0][k] for k in keys] == pytest.approx([fitted[1][0][k] for k in keys])
    for a, b in zip(read[1][2], fitted[1][2], strict=True):
        assert np.array_equal(a, b)


# --------------------------------------------------------------------------- the skip rule


def _stub_stages(sc, out: Path, calls: list, family: list):
    """The standard stages with stand-ins that record their names in ``calls``; the
    choice stand-in chooses ``family[0]``."""

    def stage(name: str, manifest: Path, **more) -> None:
        calls.append(name)
        manifest.parent.mkdir(parents=True, exist_ok=True)
        write_json({**build_manifest(sc, "", name), **more}, manifest)

    def policy(gt, gen, pol, objective, resume) -> None:
        suffix = "" if objective == "mix" else f"_{objective}"
        stage(f"train_policy{suffix}", pol / f"policy_manifest{suffix}.json")

    def choose(gt, pol) -> None:
        stage("choose_prior", pol / CHOICE_FILE, family=family[0], params={"a": 1.0})

    return standard_stages(
        out,
        lambda gt: stage("simulate", gt / "manifest.json"),
        lambda gt, gen: stage("train_generator", gen / "generator_manifest.json"),
        policy,
        lambda gt, gen, pols, ev: stage("evaluate", ev / "evaluation_manifest.json"),
        choose_prior=choose,
    )


def test_a_choice_redone_to_the_same_prior_leaves_the_policies(make_scenario, tmp_path):
    """The choice stage reads [deploy]'s safety layer (the deployment of a prior alone):
    an edit there redoes it, and the policies only where it chose another prior; an edit
    of PPO's settings redoes the policies, not the choice; the choice runs beside the
    generator (it reads the ground truth alone)."""
    sc, out = load_scenario(make_scenario()), tmp_path / "run"
    policies = ["train_policy", "train_policy_micro_only", "train_policy_macro_only"]
    family = ["idm"]

    def redone(scenario) -> list[str]:
        calls: list[str] = []
        run_stages(scenario, _stub_stages(scenario, out, calls, family), out, "", False)
        return calls

    every = ["simulate", "train_generator", "choose_prior", *policies, "evaluate"]
    assert redone(sc) == every
    assert redone(sc) == []
    sc = dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, safety_brake="matched"))
    assert redone(sc) == ["choose_prior"]
    sc = dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, safety_floor_share=0.3))
    family[0] = "gipps"
    assert redone(sc) == ["choose_prior", *policies, "evaluate"]
    sc = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, updates=3))
    assert redone(sc) == [*policies, "evaluate"]
    sc = dataclasses.replace(sc, deploy=dataclasses.replace(sc.deploy, methods=["policy"]))
    assert redone(sc) == []
