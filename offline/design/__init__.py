"""Skin design: the rest shape as an MLS warp of thickness samples, and its multi-pose optimization.

- :mod:`offline.design.mls`: affine moving-least-squares interpolation matrix and density-map sample placement.
- :mod:`offline.design.warp`: :class:`ThicknessWarp`, X(h) = X_ref + D (h − h_ref), with a harmonic depth blend.
- :mod:`offline.design.thickness`: the multi-pose problem, adjoint (Gauss-Newton or L-BFGS) and joint optimizers.
- :mod:`offline.design.ground_truth`: the block recovery test and its report and pictures.
"""
