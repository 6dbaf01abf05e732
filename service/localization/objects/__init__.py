"""Planar objects a hand holds: contours, their presets and files, and the contact field."""
