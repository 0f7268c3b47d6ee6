"""Design-time tools: skin meshing, FEM, material fitting, calibration fitting, datasets, training."""
