"""Probes of the reliability suite (``python bench/reliability.py``); the short versions run as
tests in ``tests/reliability/``. Each probe returns a :class:`~bench.reliab.common.ProbeResult`."""
