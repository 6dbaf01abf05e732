"""Imported by the local pool's fork server: compiles (or loads) the localizers' kernels
once there, so every worker forked from it starts with them ready."""

from service.episode.scenario import prepare_localizers

prepare_localizers()
