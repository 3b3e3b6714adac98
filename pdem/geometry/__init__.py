"""Walls: their shapes (:mod:`pdem.geometry.shapes`), their motions and loads
(:mod:`pdem.geometry.walls`) and the contact-geometry kernels every contact method uses (gap,
normal and closest point of a sphere against any wall kind, triangle meshes).

This package sits below :mod:`pdem.contact` and :mod:`pdem.boundaries`: it imports neither.
Plugins reach its public names through :mod:`pdem.api`.
"""
