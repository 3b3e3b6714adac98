"""``pdem advise DECK``: how much model a deck needs, and what to change to run it faster.

Reads a deck, runs at most a short probe of its first stage, and reports with reasons: the step
margins (Rayleigh time and Hertz collision time at the scene's speeds), the overlap at the scene's
stresses, the inertial number of the loading, the sample size against the published minimums, which
method (DEM-P or DEM-C) is likely faster, DEM-C's solver settings (suggested stage by stage where the
deck carries none), and the ``--set`` changes that make the run cheaper while keeping its measured
quantity. :func:`apply` writes the adjusted deck.

    from pdem.advise import advise, apply
    advice = advise("inputs/examples/direct_shear_small.toml")
    print(advice.report()); advice.changes        # {"materials.glass.youngs_modulus": ..., ...}
    apply(advice, "advised.toml")

The rules, their numbers and their sources are in :mod:`pdem.advise.rules` and ``docs/advise.md``.
"""

from .core import Advice, Finding, advise, apply, dumps_json

__all__ = ["Advice", "Finding", "advise", "apply", "dumps_json"]
