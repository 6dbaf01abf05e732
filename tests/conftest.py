"""Test-wide settings: property tests are derandomized so every run is the same run."""

from hypothesis import settings

settings.register_profile("haptic", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("haptic")
