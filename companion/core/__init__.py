"""The pure core: numpy/casadi math only (no asyncio, sockets, clocks or pymavlink).

A test (tests/test_boundaries.py) checks these imports.
"""
