"""``pdem study``: one deck run over a grid of ``--set`` overrides, as separate processes (serial or
MPI, several at a time), resumable; each run's measured quantities from its ``summary.json``, their
errors against a reference, and charts of error against wall time (both methods, Pareto fronts),
error against each knob, and a stability map.

    from pdem.study import Study
    study = Study.from_file("studies/hopper.toml")
    study.run()
    study.report()

The spec format is documented in :mod:`pdem.study.spec` and docs/study.md. :func:`launch` runs one
pdem process with a record (the building block the tools in ``tools/`` use).
"""

from .core import RunResult, Study
from .launch import RunRecord, command, launch, read_record, scan_nonfinite
from .spec import RunPlan, StudySpec, load_spec, method_label, plan_runs

__all__ = [
    "Study",
    "RunResult",
    "RunRecord",
    "RunPlan",
    "StudySpec",
    "command",
    "launch",
    "load_spec",
    "method_label",
    "plan_runs",
    "read_record",
    "scan_nonfinite",
]
