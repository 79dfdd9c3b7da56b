"""``data.section.vehicle_level``: one uniform level per (seed, run, vehicle, tag), from a
SHA-256 of the key. The digest must be hashlib's whatever implementation computes it (the
built-in one is used for speed), or deployments drawn before stop 46 would change."""

from __future__ import annotations

import hashlib

import numpy as np

from macromicro_sumo.data.section import vehicle_level


def _hashlib_level(key: str) -> float:
    return int.from_bytes(hashlib.sha256(key.encode()).digest()[:8], "little") / 2**64


def test_the_level_is_hashlibs_sha256_of_the_key() -> None:
    for seed, run, vid, tag in [
        (0, 0, "a", ""),
        (7, 3, "flow_1.42", "share"),
        (2**31, 9, "é", "x"),
    ]:
        key = f"{tag}|{seed}|{run}|{vid}" if tag else f"{seed}|{run}|{vid}"
        assert vehicle_level(seed, run, vid, tag) == _hashlib_level(key)


def test_the_levels_are_uniform_and_the_tag_separates_the_draws() -> None:
    plain = np.array([vehicle_level(1, 0, f"v{i}") for i in range(4000)])
    tagged = np.array([vehicle_level(1, 0, f"v{i}", "entry") for i in range(4000)])
    assert ((plain >= 0) & (plain < 1)).all()
    # deciles of a uniform sample of 4,000: each 400 +- 4 standard deviations (~76)
    counts = np.histogram(plain, bins=10, range=(0, 1))[0]
    assert (abs(counts - 400) < 76).all(), counts
    assert abs(np.corrcoef(plain, tagged)[0, 1]) < 0.1
