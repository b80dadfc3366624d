"""Scene files: TOML -> validated host-side ``Scene`` (SPEC section 2); ``SceneError``.

Everything here is plain Python and NumPy. A scene is validated completely before
any computation: the first problem found is raised as one ``SceneError`` whose
message starts with the field's dotted path, for example::

    materials.rock.E: must be > 0 (got -1)
    blocks.3.vertices: vertices are clockwise; list them counter-clockwise

Units as in the files (SPEC section 1): m, kN, kPa, kN/m3, angles in degrees (the
solver converts to radians). Every numeric entry is a parameter addressable by its
dotted path (``joints.set1.kn``, ``boundaries.1.traction.0``), which is what
``--set PATH=VALUE`` and ``Scene.with_overrides`` change (and the solver's choices,
``solver.linear_solver=cg``, by a word: :data:`jaxdem.scene._overrides.SOLVER_CHOICES`).

Example::

    >>> scene = load_scene("examples/two_blocks.toml", set={"joints.j.kn": 2e6})
    >>> scene.joints["j"].kn
    2000000.0

A scene may hold explicit ``[[blocks]]``, a generated rock mass (``[domain]``, joint
sets, ``[[discontinuities]]``, ``[[zones]]``, ``[[excavations]]``; the blocks themselves
are made by :func:`jaxdem.rockmass.generate`), or both. ``[in_situ]``, ``[[bolts]]``,
``[[supports]]``, ``[water]`` and ``[[stages]]`` are parsed and validated here.

Documented extensions and choices:

- ``[[boundaries]] stage`` (traction boundaries only): the stage that applies
  the traction, ramped over its load steps and kept afterwards (a surcharge
  placed after excavation); without it the traction is an initial load.
- ``[solver] regularization`` (default 1e-6, in (0, 1)), ``step_length``
  (m, optional, > 0) and ``linear_solver`` ("auto", "dense", "sparse" or "cg";
  default "auto": dense LU up to 600 unknowns (1,800 on an accelerator), else
  sparse direct on a CPU
  and matrix-free CG on an accelerator or in a batch) and ``bond_failure``
  ("events", the default, or "substep": how springs with cohesion or tensile strength
  fail) are
  jaxdem extensions.
- ``[[discontinuities]] joint`` may be left out: the line then takes the scene's
  default joint.
- ``[[blocks]] joint`` (extension): the joint of the block's faces that lie on no
  discontinuity line. With several joints, ``[scene] default_joint`` is required when an
  explicit block without ``joint`` has a face no line covers; two blocks of different
  joints may share a face only where a line says which joint it is.
- ``stage`` (excavations, bolts, supports, traction boundaries) is a stage name or its
  1-based number; a stage that does not exist (or any stage without ``[[stages]]``) is
  refused, listing the stages.
- Joint sets may give ``dip`` and ``dip_direction`` ("left", "right" or an azimuth with
  ``[scene] section_azimuth``) instead of the trace angle ``dip_deg``
  (:func:`trace_angle`).
- Explicit blocks may overlap by up to ``OVERLAP_TOLERANCE`` of the smaller block's size
  in depth (rounded coordinates).
- The user reference of all of this is docs/scene-format.md.
- ``set``/overrides may also set an optional numeric field that the file leaves out
  (``joints.j.cohesion``), when its table exists; anything else unknown is refused.
- ``load_scene`` also accepts TOML text (a string containing a newline).
- ``[[zones]] name, vertices, material`` (extension): a region of another material inside
  the domain (the seed's shear zone). Later zones override earlier ones where they overlap.
- A joint set (``dip_deg`` and ``spacing`` both given) needs a ``[domain]``. Its traces
  are parallel lines ``spacing`` apart, at ``dip_deg`` counter-clockwise from +x, one of
  them through ``origin`` (default: the domain's centroid). With ``persistence`` p < 1 each
  line carries trace segments of length ``p / (1 - p) * gap`` separated by rock bridges of
  length ``gap`` (default ``gap = spacing``), so that p is the jointed fraction of the
  line; successive lines are shifted along the trace by half a period so that bridges
  stagger. ``gap`` without p < 1, or ``gap = 0`` with p < 1, is refused (contradictory).
- ``[[excavations]]``: ``name`` is required and unique; circles and the horseshoe's roof
  are discretised into inscribed polygons of n = clip(ceil(2 pi r / h), 24, 120) segments
  around the full circle (the roof arc takes ceil(n / 2)), h = ``domain.mesh_size`` if set,
  else half the smallest joint-set spacing, else r / 4. Excavations lie inside the domain
  (touching its outline is allowed) and do not overlap each other. ``stage`` names a
  ``[[stages]]`` entry; left out: the first stage (or the only analysis). ``release``
  (extension, RS2's load split): the fractions of its load released in its stage and in
  the stages after it, each in (0, 1], summing to 1 within 1e-9, one stage for each
  (default ``[1.0]``).
- ``[in_situ] mode`` defaults to ``"gravity"``; there ``surface_y`` defaults to the top of
  the rock (highest domain or block vertex) and is stored resolved. Fields of the other
  mode are refused rather than ignored.
- Monitor points and bolt ends must lie in rock: inside the domain and not strictly inside
  an excavation, or inside an explicit block. A boundary given by ``from``/``to`` must touch
  the rock; the excavations must leave some of the domain.
- Limits, so that a typo is refused rather than run out of time or memory: ``load_steps``
  and ``max_iterations`` at most ``MAX_STEPS``; a scene that would generate more than
  ``MAX_BLOCKS`` blocks (estimated from spacings, gaps and mesh size before generating);
  polygons of more than ``MAX_POLYGON_POINTS`` vertices; files over ``MAX_FILE_BYTES``;
  ``solver.max_displacement`` above 10 model sizes, ``solver.step_length`` outside 1e-6 to
  1 model size; coordinates beyond ``MAX_OFFSET`` model sizes from (0, 0). Material and
  joint names may not contain "." (they are segments of dotted paths). A key or table
  given twice in the TOML is refused naming its path and line.

Where it lives (this module is the public face: it holds ``Scene`` and the order in which
the sections are read and checked, and imports the modules below; each of them imports
only modules listed above it):

- :mod:`jaxdem.scene._fields`: ``SceneError``, limits, the checks of one value;
- :mod:`jaxdem.scene._schema`: the records (``Material``, ``Joint``, ...) and accepted fields;
- :mod:`jaxdem.scene._properties`: ``[solver]``, ``[materials]``, ``[joints]``;
- :mod:`jaxdem.scene._checks`: polygons, overlaps, coordinates, block count, where the rock is;
- :mod:`jaxdem.scene._stages`: ``[[stages]]``, ``[water]``, stage references;
- :mod:`jaxdem.scene._rock`: blocks, discontinuities, domain, zones, excavations;
- :mod:`jaxdem.scene._loads`: boundaries, in-situ stress, bolts, supports, monitors;
- :mod:`jaxdem.scene._toml`: reading files and TOML text;
- :mod:`jaxdem.scene._overrides`: ``--set`` and ``apply_overrides``.
"""

from jaxdem.scene._checks import OVERLAP_TOLERANCE, overlap_depth  # noqa: I001 (records packed)
from jaxdem.scene._fields import SceneError
from jaxdem.scene._overrides import apply_overrides, parse_set_arguments
from jaxdem.scene._parse import Scene, load_scene, parse_scene
from jaxdem.scene._properties import trace_angle
from jaxdem.scene._schema import (
    Block, Bolt, Boundary, Discontinuity, Domain, Excavation, InSitu, Joint, Material, Monitor,
    SolverSettings, Stage, Support, Water, Zone)
from jaxdem.scene._toml import MAX_FILE_BYTES

__all__ = ["MAX_FILE_BYTES", "OVERLAP_TOLERANCE", "Block", "Bolt", "Boundary", "Discontinuity",
           "Domain", "Excavation", "InSitu", "Joint", "Material", "Monitor", "Scene", "SceneError",
           "SolverSettings", "Stage", "Support", "Water", "Zone", "apply_overrides", "load_scene",
           "overlap_depth", "parse_scene", "parse_set_arguments", "trace_angle"]
