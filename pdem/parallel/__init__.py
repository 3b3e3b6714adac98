"""MPI layer: communicator helpers, decomposition and ghost exchange.

Importing it sets MPICH's tuning defaults before mpi4py starts MPI (pdem imports mpi4py lazily,
always after this package): see :data:`MPICH_DEFAULTS`.
"""

from __future__ import annotations

import os

#: MPICH settings pdem changes from MPICH's defaults (a variable already in the environment wins;
#: other MPI libraries ignore them). Read by MPI_Init, so they apply only if mpi4py had not started
#: MPI before pdem was imported.
#:
#: - ``MPIR_CVAR_CH4_IPC_CMA_P2P_THRESHOLD``: MPICH sends a message of 8 KiB or more between ranks
#:   of one node by CMA (the receiver reads the sender's memory with process_vm_readv after a
#:   rendezvous handshake). pdem's ghost forwards, sent at every step, are 10–100 KiB, and the
#:   handshake made them cost twice what a copy through MPICH's shared-memory queue does: on the
#:   18k column's 2 ranks 57–70 against 30–36 µs a forward, loop time 28.8 against 24.7 s (medians
#:   of 3 alternating pairs, 25,000 steps; measured at commit a6785a5). CMA is kept for messages from 1 MiB.
MPICH_DEFAULTS = {"MPIR_CVAR_CH4_IPC_CMA_P2P_THRESHOLD": str(1 << 20)}

for _name, _value in MPICH_DEFAULTS.items():
    os.environ.setdefault(_name, _value)
