"""MPI layer: communicator helpers, decomposition and ghost exchange."""
