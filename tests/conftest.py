"""Suite-wide settings. Hypothesis' per-example deadline (200 ms) is a timed assertion: on a
loaded 2-core CI machine it failed property tests that were correct. Speed lives in bench/."""

from hypothesis import settings

settings.register_profile("suite", deadline=None)
settings.load_profile("suite")
