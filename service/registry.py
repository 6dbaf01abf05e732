"""Named implementations chosen at run time (localizers, policies, backends).

Entries are "module:attribute" strings imported on first use, so `service` never imports a
concrete backend at module level and the CLI can list everything without loading it.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from service.errors import ConfigError


@dataclass(frozen=True)
class Entry:
    target: str
    summary: str


class Registry:
    def __init__(self, kind: str, entries: dict[str, Entry]) -> None:
        self.kind = kind
        self.entries = entries

    def names(self) -> list[str]:
        return list(self.entries)

    def help(self) -> str:
        return "; ".join(f"{name}: {e.summary}" for name, e in self.entries.items())

    def load(self, name: str) -> Any:
        entry = self.entries.get(name)
        if entry is None:
            raise ConfigError(f"unknown {self.kind} '{name}'; choose one of: "
                              f"{', '.join(self.entries)}")
        module, _, attr = entry.target.partition(":")
        return getattr(importlib.import_module(module), attr)


LOCALIZERS = Registry("algorithm", {
    "elimination": Entry("service.localization.localizers.elimination:Elimination",
                         "Algorithm III, process of elimination over a pose table"),
    "grid": Entry("service.localization.localizers.grid:Grid",
                  "Algorithm I, position (and heading) probability grid"),
    "match": Entry("service.localization.localizers.match:Match",
                   "Algorithm II, probability grid plus pattern matching of the readings"),
    "particles": Entry("service.localization.localizers.particles:Particles",
                       "Algorithm IV, evolutionary Monte Carlo with a bounded pool"),
})

OBJECT_LOCALIZERS = Registry("algorithm", {
    "particles": Entry("service.localization.localizers.object_particles:ObjectParticles",
                       "Algorithm IV on the held object's pose"),
    "elimination": Entry("service.localization.localizers.object_elimination:ObjectElimination",
                         "Algorithm III: a table of object poses, each reading eliminating"),
})
"""Localizers of an object held by a hand (`haptic run --object`)."""

POLICIES = Registry("policy", {
    "paper": Entry("service.localization.policies.paper:PaperPolicy",
                   "the paper's heuristic: the move 10 sampled candidates disagree on most"),
    "random": Entry("service.localization.policies.paper:RandomPolicy", "a random unblocked move"),
    "info-gain": Entry("service.localization.policies.info_gain:InfoGainPolicy",
                       "the move with the largest expected information about the pose"),
})

BACKENDS = Registry("backend", {
    "sim": Entry("sim_backend.finger:SimulatedFinger", "simulated finger on the map"),
    "dynamixel": Entry("firmware_if.dynamixel_backend:DynamixelBackend",
                       "Dynamixel servos on --port, hand from --hand"),
})
