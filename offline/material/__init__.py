"""Material fitting: virtual standard tests (uniaxial tension/compression) and hyperelastic parameter fitting.

Modules:

- :mod:`offline.material.models` — the fitted hyperelastic models (neo-Hookean, Mooney-Rivlin, Yeoh) described by
  the small-strain pair (E, ν) plus model-specific shape parameters, and their conversion to FEM materials.
- :mod:`offline.material.closed_form` — the homogeneous uniaxial answer (lateral stress zero), exact for
  frictionless grips; used as the cheap surrogate in fitting.
- :mod:`offline.material.specimen` — standard specimen geometries (strip 55 × 5 × 2 mm, cylinder ⌀50 × 12 mm).
- :mod:`offline.material.measurements` — loading and validating measured force–strain files.
- :mod:`offline.material.virtual_test` — the FEM virtual uniaxial test (frictionless or clamped grips).
- :mod:`offline.material.fit` — simulated annealing and least-squares fits.
- :mod:`offline.material.plot` — measured versus simulated curves (PNG).
- :mod:`offline.cli.uniaxial` and :mod:`offline.cli.fit_material` — ``likeness offline uniaxial`` and
  ``likeness offline fit-material``.

Heavy modules (FEM, matplotlib) are imported only where needed.
"""

DEFAULT_E = 78_000.0
"""Default Young's modulus (Pa) when nothing is fitted: the cured skin silicone of the source paper."""

DEFAULT_NU = 0.47
"""Default Poisson's ratio when nothing is fitted."""
