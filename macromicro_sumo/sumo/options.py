"""SUMO's command line, built explicitly (``sumo.simulation`` starts SUMO with it)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class SumoOptions:
    """Everything that goes on SUMO's command line."""

    net_file: Path
    additional_files: tuple[Path, ...]
    step_length_s: float
    seed: int
    error_log: Path | None = None
    fcd_file: Path | None = None  # SUMO floating-car-data output (evaluation rollouts)
    route_files: tuple[Path, ...] = ()  # a user's demand (sections); the ring has none
    # The ring places its vehicles exactly and checks them itself; a user's demand keeps
    # SUMO's own insertion checks and teleports, as the user's runs have them.
    user_demand: bool = False
    # SUMO's random streams for driving (dawdling, lane changing): None keeps SUMO's default
    # (64, one per lane modulo 64); another count re-maps them, so the same demand,
    # departures and speed factors (SUMO's parsing stream) meet other random draws.
    rng_streams: int | None = None

    def args(self) -> list[str]:
        args = [
            "-n", str(self.net_file),
            "--step-length", repr(float(self.step_length_s)),
            "--seed", str(int(self.seed)),
            # Collisions are only reported: learning needs every vehicle kept.
            "--collision.action", "warn",
            "--no-step-log", "true",
            "--duration-log.disable", "true",
            "--no-warnings", "true",
        ]  # fmt: skip
        if not self.user_demand:
            # No teleports; our vehicles are placed exactly where the data says and we
            # verify insertion ourselves.
            args += ["--time-to-teleport", "-1", "--insertion-checks", "none"]
        if self.route_files:
            args += ["-r", ",".join(str(p) for p in self.route_files)]
        if self.additional_files:
            args += ["-a", ",".join(str(p) for p in self.additional_files)]
        if self.fcd_file is not None:
            args += ["--fcd-output", str(self.fcd_file)]
        if self.rng_streams is not None:
            args += ["--thread-rngs", str(int(self.rng_streams))]
        if self.error_log is not None:
            args += ["--error-log", str(self.error_log)]
        return args
