"""The public plugin API: everything a contact law, boundary, writer, integrator or particle-field
plugin needs, in one import. Plugins (pdem's own included) import from here or from pdem's public
modules, never from a private module (a name starting with ``_``); a test enforces it.

Contact laws (``pdem.contact_laws``)
    :class:`ContactLaw`, :class:`LawParams`; the kernel toolkit :func:`njit` (pdem's numba
    configuration: cache on, fastmath off), the generic loops :func:`pair_forces` and
    :func:`wall_forces`, :func:`tangential_spring` (history, Coulomb cap) and the flag bits
    ``FLAG_OVERLAP``, ``FLAG_NONFINITE``, ``FLAG_COINCIDENT``; contract checks in
    :mod:`pdem.testing.law_contract`. A law whose force can be computed on columns (vectorized)
    runs the pair loop in passes: :func:`touching_pairs` (the touching test of every listed pair),
    then, a block of touching pairs at a time, :func:`fill_pair_columns` (their geometry into the
    rows ``COL_*``), its own loop over the columns (writing the rows ``OUT_*``; branch-free helpers
    such as :func:`tangential_spring_values` and :func:`tangential_mindlin_values`) and
    :func:`scatter_pair_columns`, as Hertz–Mindlin does; :func:`pair_columns` is the first two in
    one call.
Methods with their own time step
    :class:`Integrator` (returned by ``ContactLaw.make_integrator``), :class:`VelocityVerlet`, the
    wall geometry kernel :func:`wall_contact` (gap, normal, closest point of any wall kind) and
    :func:`surface_velocity` (a wall's velocity at a point: translation, rotation, radius rate);
    partition-independent sums inside kernels: :func:`exact_accumulator`, :func:`exact_add` (or
    :func:`exact_add_many` with :func:`exact_bins` for up to 1024 terms at once, faster),
    :func:`exact_partials` (combine ranks with :func:`pdem.parallel.exact.exact_reduce`);
    :func:`column_partials`: a column of terms as a few doubles whose exact sum is theirs.
Boundaries (``pdem.boundaries``)
    :class:`Boundary`, :class:`BoundaryParams`, :class:`WallBoundaryParams`, :data:`Vec3`,
    :data:`MotionSpec`, :func:`make_motion`; walls: :class:`Wall`, :mod:`shapes`, the motions
    :class:`Motion`, :class:`Fixed`, :class:`ConstantVelocity`, :class:`VelocityFunction`,
    :class:`PositionFunction`, :class:`Controlled` (velocities set by a controller),
    :class:`Rotation`, :class:`Resize` (named sizes: radius, length, …), :class:`Follow` (moves with
    another wall), :class:`RigidBody` (a wall moved by its load), :func:`rotation_matrix`; velocity
    servos: :func:`servo_gain` (a proportional gain capped so the loop stays stable at the step,
    from :func:`wall_stiffness`, the stiffness of a wall's contacts); what the boundary tells
    ``pdem advise``: :class:`Loading`, :class:`Extent`, :class:`SampleSize`, :class:`SizeCheck`,
    given :class:`SceneFacts`.
Writers (``pdem.writers``)
    :class:`Writer`, :class:`Frame`, :class:`WallState`, :class:`Piece`, :func:`atomic_write_text`,
    :func:`piece_name`, :func:`safe_key`, :data:`KIND_NAMES`, :func:`wall_triangles`.
Particles
    :class:`Field` (``Simulation.register_field``), :func:`dof_mask`, the motion codes ``FREE``,
    ``FIXED``, ``PRESCRIBED``, ``REMOVED``; :class:`ContactStore`.
Collectives (every rank calls them; one rank's values returned as is)
    :func:`any_rank`, :func:`all_max`, :func:`all_min`, :func:`all_max_array`,
    :func:`all_sum_int_array`; a boundary's stage test :func:`listed`.
Everything
    :class:`Simulation`, :class:`Material`, :class:`MaterialTable`, :func:`effective_moduli` (E*,
    G* of a material pair), :func:`damping_ratio` (β of a restitution coefficient), the typed errors.
"""

from __future__ import annotations

from ._jit import njit
from .boundaries.api import (
    STAGE_COLUMN,
    Boundary,
    BoundaryParams,
    Extent,
    Loading,
    MotionSpec,
    SampleSize,
    SceneFacts,
    SizeCheck,
    Vec3,
    WallBoundaryParams,
    listed,
    make_motion,
    merge_series,
    stage_rows,
)
from .contact._kernels import (
    COL_AI,
    COL_AJ,
    COL_DELTA,
    COL_HIST,
    COL_IEFF,
    COL_MEFF,
    COL_NX,
    COL_NY,
    COL_NZ,
    COL_REFF,
    COL_VX,
    COL_VY,
    COL_VZ,
    COL_WX,
    COL_WY,
    COL_WZ,
    FLAG_COINCIDENT,
    FLAG_NONFINITE,
    FLAG_OVERLAP,
    OUT_FX,
    OUT_FY,
    OUT_FZ,
    OUT_HIST,
    OUT_MX,
    OUT_MY,
    OUT_MZ,
    fill_pair_columns,
    pair_columns,
    pair_forces,
    scatter_pair_columns,
    touching_pairs,
    wall_forces,
)  # fmt: skip
from .contact._tangential import tangential_mindlin_values, tangential_spring, tangential_spring_values
from .contact.law import ContactLaw, LawParams, ListNeeds
from .contact.stability import servo_gain, wall_stiffness
from .contact.store import ContactStore
from .errors import (
    CheckpointError,
    DeckError,
    GeometryError,
    InputError,
    InstabilityError,
    NumericalError,
    OutputError,
    PdemError,
    PluginError,
)
from .geometry import shapes
from .geometry._kernels import KIND_NAMES, surface_velocity, wall_contact
from .geometry.walls import (
    ConstantVelocity,
    Controlled,
    Fixed,
    Follow,
    Motion,
    PositionFunction,
    Resize,
    RigidBody,
    Rotation,
    VelocityFunction,
    Wall,
    rotation_matrix,
)
from .integrate.base import Integrator
from .integrate.verlet import VelocityVerlet
from .io.base import Piece, Writer, atomic_write_text, piece_name, safe_key
from .io.frame import Frame, WallState
from .io.wall_mesh import wall_triangles
from .materials import Material, MaterialTable, damping_ratio, effective_moduli
from .parallel.comm import all_max, all_max_array, all_min, all_sum_int_array, any_rank
from .parallel.exact import (
    column_partials,
    exact_accumulator,
    exact_add,
    exact_add_many,
    exact_bins,
    exact_partials,
)
from .simulation import Simulation
from .state.particles import FIXED, FREE, PRESCRIBED, REMOVED, Field, dof_mask

__all__ = [
    "njit", "pair_forces", "wall_forces", "tangential_spring", "wall_contact", "surface_velocity",
    "pair_columns", "touching_pairs", "fill_pair_columns", "scatter_pair_columns", "tangential_spring_values",
    "tangential_mindlin_values",
    "COL_DELTA", "COL_NX", "COL_NY", "COL_NZ", "COL_VX", "COL_VY", "COL_VZ", "COL_WX", "COL_WY", "COL_WZ",
    "COL_REFF", "COL_MEFF", "COL_IEFF", "COL_AI", "COL_AJ", "COL_HIST",
    "OUT_FX", "OUT_FY", "OUT_FZ", "OUT_MX", "OUT_MY", "OUT_MZ", "OUT_HIST",
    "exact_accumulator", "exact_add", "exact_add_many", "exact_bins", "exact_partials", "column_partials",
    "KIND_NAMES",
    "FLAG_OVERLAP", "FLAG_NONFINITE", "FLAG_COINCIDENT",
    "ContactLaw", "LawParams", "ListNeeds", "ContactStore", "Integrator", "VelocityVerlet",
    "Boundary", "BoundaryParams", "WallBoundaryParams", "Vec3", "MotionSpec", "make_motion",
    "STAGE_COLUMN", "merge_series", "stage_rows", "listed",
    "Loading", "Extent", "SampleSize", "SizeCheck", "SceneFacts",
    "any_rank", "all_max", "all_min", "all_max_array", "all_sum_int_array",
    "Wall", "shapes", "Motion", "Fixed", "ConstantVelocity", "VelocityFunction", "PositionFunction",
    "Controlled", "Rotation", "Resize", "RigidBody", "Follow", "rotation_matrix",
    "servo_gain", "wall_stiffness",
    "Writer", "Frame", "WallState", "Piece", "atomic_write_text", "piece_name", "safe_key",
    "wall_triangles",
    "Field", "dof_mask", "FREE", "FIXED", "PRESCRIBED", "REMOVED",
    "Simulation", "Material", "MaterialTable", "damping_ratio", "effective_moduli",
    "PdemError", "InputError", "DeckError", "PluginError", "GeometryError", "NumericalError",
    "InstabilityError", "CheckpointError", "OutputError",
]  # fmt: skip
