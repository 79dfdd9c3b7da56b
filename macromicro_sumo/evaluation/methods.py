"""The methods an evaluation compares, in one registry: what each is and where it runs.

Every evaluation (the ring's and a section's), the policy folder's checkpoint names and the
report read this table, so a new baseline is one entry here plus its action function.
"""

from __future__ import annotations

from dataclasses import dataclass

from macromicro_sumo.policy.checkpoint import policy_file


@dataclass(frozen=True)
class Method:
    """One row of the macro-alignment tables.

    Attributes:
        name: the ``method`` column value.
        role: ``reference`` (the recording), ``learned`` (a policy trained by PPO),
            ``baseline`` (what an engineer would calibrate) or ``oracle`` (a bound that
            knows what the method cannot).
        what: one line for the report.
        objective: the PPO objective that trains it (learned methods only).
        roads: the scenario kinds it runs on (``ring``: the paper's fleet of known IDM
            parameters; ``sumo``: a section of the user's network; ``idm_true`` there only
            where the truth records each vehicle's IDM parameters, a ``[fleet]`` demand:
            ``evaluation.idm_true``).
    """

    name: str
    role: str
    what: str
    objective: str = ""
    roads: tuple[str, ...] = ("ring", "sumo")


METHODS: tuple[Method, ...] = (
    Method("ground_truth", "reference", "the recorded vehicles on the true scene"),
    Method("policy", "learned", "the paper's objective, r_micro + eta r_macro", "mix"),
    Method("micro_only", "learned", "ablation: the micro likelihood only (eta = 0)", "micro_only"),
    Method("macro_only", "learned", "ablation: the macro reward only", "macro_only"),
    Method(
        "idm_calibrated", "baseline", "one IDM fitted by least squares to the observed vehicles"
    ),
    Method(
        "idm_true",
        "oracle",
        "each hidden vehicle's own IDM parameters, given to the generated vehicle it is matched to",
    ),
)
BY_NAME = {m.name: m for m in METHODS}


def method_order(road: str) -> list[str]:
    """The methods of a scenario kind (``ring`` or ``sumo``), in the tables' order."""
    return [m.name for m in METHODS if road in m.roads]


def checkpoint_name(method: Method) -> str:
    """The file a learned method's policy is saved as in a policy folder."""
    return policy_file(method.objective)


LEARNED = tuple(m for m in METHODS if m.role == "learned")


def methods_markdown(road: str, present: set[str]) -> list[str]:
    """Report lines: what each method of the table is (those in ``present``)."""
    rows = [m for m in METHODS if road in m.roads and m.name in present]
    return [f"- `{m.name}` ({m.role}): {m.what}." for m in rows] + [""]
