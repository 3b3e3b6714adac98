"""Shared pytest configuration: long runs are opt-in with --runslow.

The MPI tests run 3-4 ranks on 2-core machines. MPICH's ranks busy-poll while they wait, so an
oversubscribed rank waits for a descheduled one at every exchange; letting idle ranks sleep a
microsecond (MPIR_CVAR_CH4_PROGRESS_THROTTLE) made a 4-rank DEM-C hopper run 1.4-1.6x faster on
such a machine. It changes timing only, never results. The launched processes inherit it.
"""

import os

import pytest

os.environ.setdefault("MPIR_CVAR_CH4_PROGRESS_THROTTLE", "1")


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run tests marked slow (full experiments, large scenes)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
