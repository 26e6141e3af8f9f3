"""Scene-level train/val/test splits that keep locations and conditions balanced.

A clip is a scene: all its frames go to one split, otherwise near-identical neighbouring
frames leak between train and test. Clips are stratified by (location, weather, lighting);
inside a stratum they are ordered by a seeded hash of their id (deterministic, independent
of query order and of which other clips exist), and each clip goes to the split whose
quota is most behind, counting both the stratum and the whole release, so small strata
(one clip of snow at night) do not all end up in train while the totals stay on target.
"""

from __future__ import annotations

import hashlib
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class SceneKey:
    clip_id: str
    location: str
    weather: str
    lighting: str

    @property
    def stratum(self) -> tuple[str, str, str]:
        return (self.location, self.weather, self.lighting)


@dataclass(frozen=True)
class SplitConfig:
    fractions: tuple[float, float, float] = (0.70, 0.15, 0.15)
    seed: int = 0

    def __post_init__(self) -> None:
        if len(self.fractions) != 3 or any(f < 0 for f in self.fractions):
            raise ValueError("fractions must be three non-negative numbers")
        if abs(sum(self.fractions) - 1.0) > 1e-6:
            raise ValueError(f"fractions must sum to 1, got {sum(self.fractions)}")


def _order_key(seed: int, clip_id: str) -> str:
    return hashlib.sha256(f"{seed}:{clip_id}".encode()).hexdigest()


def assign_splits(scenes: Sequence[SceneKey],
                  config: SplitConfig = SplitConfig()) -> dict[str, str]:
    """clip_id -> "train" | "val" | "test"; deterministic for a given set and seed."""
    ids = [s.clip_id for s in scenes]
    if len(set(ids)) != len(ids):
        raise ValueError("duplicate clip ids")
    strata: dict[tuple[str, str, str], list[SceneKey]] = defaultdict(list)
    for s in scenes:
        strata[s.stratum].append(s)
    fr = config.fractions
    total = [0, 0, 0]
    out: dict[str, str] = {}
    n_done = 0
    # big strata first: they set the global balance, small ones fill the gaps
    for key in sorted(strata, key=lambda k: (-len(strata[k]), k)):
        members = sorted(strata[key], key=lambda s: _order_key(config.seed, s.clip_id))
        local = [0, 0, 0]
        for i, scene in enumerate(members):
            scores = [(fr[j] * (i + 1) - local[j] + fr[j] * (n_done + 1) - total[j], fr[j], -j)
                      for j in range(3)]
            j = max(range(3), key=scores.__getitem__)
            local[j] += 1
            total[j] += 1
            n_done += 1
            out[scene.clip_id] = SPLITS[j]
    return out


def split_counts(splits: dict[str, str]) -> dict[str, int]:
    return {name: sum(1 for v in splits.values() if v == name) for name in SPLITS}
